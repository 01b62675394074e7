"""``cva-mask``: draw the node's ignore mask (``mask_path``) from the command line.

The camera of a robot often sees the robot: a bumper in the lower corners, an arm, a mast. The
node publishes nothing at the black pixels of its mask (:mod:`cva_confidence_ros.mask`), so
that they never become points or obstacles. Any image editor draws one on a frame of the
camera; this command does it on a robot without one, from rectangles, polygons and whole rows,
and takes the size and a frame to check it on from the robot's own bag::

    cva-mask mask.png --bag robot_bag --below 400 --polygon 0,300 120,479 0,479
    cva-mask mask.png --size 640x480 --rect 560 380 640 480
    cva-mask mask.png --start mask.png --overwrite --rect 0 0 40 40   # add to a mask

With a frame (``--bag`` or ``--image``) it also writes ``<mask>_preview.png``: the frame with
the ignored pixels shaded red, to look at before the robot drives with it. It prints what the
mask leaves: the share ignored and the rows processed (rows black from edge to edge at the top
or bottom are skipped, as with ``roi_top`` / ``roi_bottom``).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import stat
import sys
import tempfile
from typing import Any

import cv2
import numpy as np

from cva_confidence_ros.datasets.io import decode_image_file
from cva_confidence_ros.errors import BagError, ConfigError, CVAError, DataError, InputError
from cva_confidence_ros.mask import load_mask, mask_rows
from cva_confidence_ros.outputs import check_output_file

__all__ = ['build_parser', 'draw_mask', 'frame_from_bag', 'main']

_IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
_INT32_MAX = 2**31 - 1


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``cva-mask``."""
    parser = argparse.ArgumentParser(
        prog='cva-mask',
        description="Draw an ignore mask for the node's mask_path: black where the camera "
                    "sees the robot's own body.",
    )
    parser.add_argument('out', type=Path,
                        help='mask PNG to write, named .png (0 = ignore, 255 = judge)')
    size = parser.add_mutually_exclusive_group()
    size.add_argument('--size', metavar='WxH', help='image size in pixels, e.g. 640x480')
    size.add_argument('--image', type=Path, help='a frame of the camera (size and preview)')
    size.add_argument('--bag', type=Path, help='a rosbag2 of the camera (size and preview '
                                               'from one of its left images)')
    parser.add_argument('--start', type=Path,
                        help='an existing mask to add to (gives the size without the others)')
    parser.add_argument('--topic', help='image topic of --bag (default: its one image topic '
                                        "with 'left' in the name, raw or compressed)")
    parser.add_argument('--frame', type=int,
                        help='which message of the topic to show (default 0 = first)')
    parser.add_argument('--rect', type=int, nargs=4, action='append', default=[],
                        metavar=('X0', 'Y0', 'X1', 'Y1'),
                        help='ignore the pixels with X0 <= x < X1 and Y0 <= y < Y1 (repeatable)')
    parser.add_argument('--polygon', nargs='+', action='append', default=[], metavar='X,Y',
                        help='ignore the inside of a polygon of 3 or more corners (repeatable)')
    parser.add_argument('--below', type=int, metavar='Y',
                        help='ignore row Y and every row below it (a hood or bumper)')
    parser.add_argument('--above', type=int, metavar='Y',
                        help='ignore every row above row Y')
    parser.add_argument('--preview', type=Path,
                        help='where to write the preview (default: <out>_preview.png, with a '
                             'frame only)')
    parser.add_argument('--overwrite', action='store_true', help='replace existing files')
    return parser


def _parse_size(text: str) -> tuple[int, int]:
    parts = text.lower().split('x')
    # isdecimal, not isdigit: '4²' is a digit to Python, but not a number int() reads
    if len(parts) != 2 or not all(part.strip().isdecimal() for part in parts):
        raise ConfigError(f'--size must be WIDTHxHEIGHT in pixels, e.g. 640x480; got {text!r}')
    width, height = (int(part) for part in parts)
    if width <= 0 or height <= 0:
        raise ConfigError(f'--size must be positive; got {text!r}')
    return width, height


def _parse_polygon(corners: list[str]) -> np.ndarray:
    points = []
    for corner in corners:
        parts = corner.split(',')
        try:
            x, y = (int(part) for part in parts)
        except ValueError:
            raise ConfigError(
                f'--polygon corners must be X,Y in whole pixels; got {corner!r}'
            ) from None
        if max(abs(x), abs(y)) > _INT32_MAX:  # OpenCV takes 32-bit corners
            raise ConfigError(
                f'--polygon corners must lie within ±{_INT32_MAX} px; got {corner!r}'
            )
        points.append((x, y))
    if len(points) < 3:
        raise ConfigError(f'--polygon needs 3 corners or more; got {len(points)}: {corners}')
    return np.asarray(points, dtype=np.int32)


def _polygon_corners(polygon: Any) -> np.ndarray:
    """``polygon`` as the (N, 2) int32 corners OpenCV fills, checked as ``--polygon`` is: a
    line or a point would be drawn as such, corners past int32 would wrap around."""
    try:
        points = np.asarray(polygon)
    except ValueError:  # corners of different lengths
        points = np.asarray(polygon, dtype=object)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ConfigError(
            f'a polygon must be (N, 2) corners (x, y); got shape {points.shape}: {polygon!r}'
        )
    if points.dtype.kind not in 'iu':
        raise ConfigError(
            f'polygon corners must be whole pixels (integers); got {points.dtype}: '
            f'{points.tolist()}'
        )
    if len(points) < 3:
        raise ConfigError(f'a polygon needs 3 corners or more; got {len(points)}: '
                          f'{points.tolist()}')
    if np.abs(points.astype(np.float64)).max() > _INT32_MAX:  # OpenCV takes 32-bit corners
        raise ConfigError(
            f'polygon corners must lie within ±{_INT32_MAX} px; got {points.tolist()}'
        )
    return points.astype(np.int32)


def draw_mask(
    width: int,
    height: int,
    *,
    start: np.ndarray | None = None,
    rects: list[list[int]] | tuple[()] = (),
    polygons: list[np.ndarray] | tuple[()] = (),
    below: int | None = None,
    above: int | None = None,
) -> np.ndarray:
    """An ignore mask of ``width`` × ``height``: (H, W) bool, False = ignore.

    Args:
        start: A mask to add to (True or nonzero = judged), or None for all judged.
        rects: ``[x0, y0, x1, y1]``, each ignoring ``x0 ≤ x < x1``, ``y0 ≤ y < y1`` (clipped
            to the image; one that leaves no pixel of the image is refused).
        polygons: (N, 2) int corners (x, y) (an array or a list of pairs), N ≥ 3, within
            ±(2³¹ − 1), each ignoring its inside and edges (one that leaves no pixel of the
            image is refused).
        below: Ignore rows ``y ≥ below``. above: Ignore rows ``y < above``.

    Raises:
        ConfigError: A rectangle, polygon or row outside the image, a polygon that is not
            one (fewer than 3 corners, not whole pixels), or the wrong size of ``start``.
    """
    # A copy as bool: a 0/255 start mask would otherwise come back as 0/1 uint8 after &=
    keep = np.ones((height, width), dtype=bool) if start is None else np.array(start, bool)
    if keep.shape != (height, width):
        raise ConfigError(f'the start mask is {keep.shape[1]}×{keep.shape[0]} px, not '
                          f'{width}×{height}')
    for rect in rects:
        x0, y0, x1, y1 = rect
        cx0, cy0 = max(x0, 0), max(y0, 0)
        cx1, cy1 = min(x1, width), min(y1, height)
        if cx0 >= cx1 or cy0 >= cy1:
            raise ConfigError(
                f'--rect {x0} {y0} {x1} {y1} covers no pixel of the {width}×{height} image '
                f'(X0 < X1 and Y0 < Y1, inside it)'
            )
        keep[cy0:cy1, cx0:cx1] = False
    for polygon in map(_polygon_corners, polygons):
        # One at a time: a polygon off the image (a typo, x and y swapped) is refused, as a
        # rectangle is, instead of silently ignoring nothing.
        canvas = np.zeros((height, width), dtype=np.uint8)
        cv2.fillPoly(canvas, [polygon], 255)
        if not canvas.any():
            corners = ' '.join(f'{x},{y}' for x, y in np.asarray(polygon).reshape(-1, 2))
            raise ConfigError(
                f'--polygon {corners} covers no pixel of the {width}×{height} image'
            )
        keep &= canvas == 0
    for name, row in (('--below', below), ('--above', above)):
        if row is not None and not 0 <= row <= height:
            raise ConfigError(f'{name} must be a row in [0, {height}]; got {row}')
    if below is not None:
        keep[below:] = False
    if above is not None:
        keep[:above] = False
    return keep


def frame_from_bag(bag_path: Path, topic: str | None, index: int) -> np.ndarray:
    """The ``index``-th image on ``topic`` of a rosbag2, decoded as the node decodes it.

    Raises:
        BagError: No such topic (the image topics are named), fewer messages, or a message
            that is not a valid one of its type (corrupt or truncated data).
        InputError: An image the node could not decode either.
    """
    from cva_confidence_ros.ros.convert import image_to_array
    from msg_tools.bagio import InputBag, deserialize
    from msg_tools.convert import jazzy_typestore

    if index < 0:
        raise ConfigError(f'--frame must be >= 0; got {index}')
    store = jazzy_typestore()
    with InputBag(bag_path) as bag:
        images = {name: kind for name, kind in bag.topics.items() if kind in _IMAGE_TYPES}
        if topic is None:
            left = sorted(name for name in images if 'left' in name)
            if len(left) != 1:
                raise BagError(
                    f'bag {bag_path} has {len(left)} image topics with "left" in the name; '
                    f'name one with --topic (image topics: {sorted(images) or "none"})'
                )
            topic = left[0]
        elif topic not in images:
            raise BagError(
                f'bag {bag_path} has no image topic {topic!r}; image topics: '
                f'{sorted(images) or "none"}'
            )
        for count, (_, kind, _, data) in enumerate(bag.messages([topic])):
            if count == index:
                msg: Any = deserialize(
                    store, data, kind, f'message {index} on {topic} of bag {bag_path}'
                )
                return image_to_array(msg, f'{topic} message {index}')
        raise BagError(f'bag {bag_path} has no message {index} on {topic} (numbered from 0)')


def preview(image: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The frame (RGB) with the ignored pixels shaded red and a yellow line on the skipped
    rows next to the processed ones (the row above the first, the row below the last)."""
    from cva_confidence_ros.ros.convert import pair_to_uint8

    gray_or_rgb = pair_to_uint8(image, image)[0]  # 16-bit frames scaled as the node scales them
    if gray_or_rgb.ndim == 2:
        gray_or_rgb = np.repeat(gray_or_rgb[..., None], 3, axis=2)
    rgb = gray_or_rgb.astype(np.float32)
    red = np.array([255.0, 0.0, 0.0], dtype=np.float32)
    rgb[~keep] = 0.45 * rgb[~keep] + 0.55 * red
    y0, y1 = mask_rows(keep)
    out = rgb.astype(np.uint8)
    for row in (y0 - 1, y1):
        if 0 <= row < out.shape[0]:
            out[row] = (255, 220, 0)
    return out


def _write_atomically(path: Path, rgb_or_gray: np.ndarray) -> None:
    """PNG write through a temporary file in the same folder, so that a failed write leaves
    an existing file as it was (the folder is made by ``check_output_file`` before)."""
    pixels = rgb_or_gray if rgb_or_gray.ndim == 2 else cv2.cvtColor(rgb_or_gray,
                                                                    cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode('.png', pixels)
    if not ok:
        raise InputError(f'could not encode {path} as PNG')
    handle, temporary = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        # mkstemp makes the file 0600, which a node running as another user (a service, a
        # container) could not read: a replaced file keeps its mode, a new one gets the umask's.
        os.fchmod(handle, _file_mode(path))
        with os.fdopen(handle, 'wb') as stream:
            stream.write(data.tobytes())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def _file_mode(path: Path) -> int:
    """Permissions for a file written at ``path``: those of the file it replaces, or those
    ``open`` gives a new one (0666 less the umask)."""
    try:
        return stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def summary(keep: np.ndarray) -> str:
    """One line on what a mask leaves: share ignored and rows processed."""
    height, width = keep.shape
    ignored = int(np.count_nonzero(~keep))
    y0, y1 = mask_rows(keep)
    rows = (f'rows {y0} to {y1 - 1} processed, {height - (y1 - y0)} of {height} skipped (black '
            f'from edge to edge)' if (y0, y1) != (0, height) else f'all {height} rows processed')
    return f'{width}×{height} px, {ignored / keep.size:.1%} ignored ({ignored} px); {rows}'


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cva-mask``; returns the exit code (2 on bad input)."""
    args = build_parser().parse_args(argv)
    try:
        if args.out.suffix.lower() != '.png':
            # The mask is written as PNG whatever the name: one named .jpg was then refused
            # by the node as a truncated JPEG (the name decides how it is checked).
            raise ConfigError(f'out {args.out} must be named .png: cva-mask writes a PNG mask')
        if args.preview is not None and args.preview.resolve() == args.out.resolve():
            raise ConfigError(
                f'--preview {args.preview} is the mask {args.out} itself: the preview would '
                'replace the mask; give the preview another name'
            )
        if args.bag is None:
            # They pick the frame of a bag: without one they would be silently ignored.
            for name, value in (('--topic', args.topic), ('--frame', args.frame)):
                if value is not None:
                    raise ConfigError(f'{name} {value} picks a message of --bag; there is no '
                                      f'--bag to pick it from')
        frame = None
        start = None if args.start is None else load_mask(args.start, '--start')
        if args.size is not None:
            width, height = _parse_size(args.size)
        elif args.image is None and args.bag is None:
            if start is None:
                raise ConfigError('give the size: --size, --image, --bag or --start')
            height, width = start.shape
        else:
            if args.image is not None:
                try:
                    # Header size checked before decoding; a truncated JPEG refused.
                    frame = decode_image_file(args.image)
                except DataError as exc:
                    raise InputError(f'--image {args.image} cannot be used: {exc}') from None
                if frame is None or frame.size == 0:
                    raise InputError(f'--image {args.image} cannot be read as an image')
                if frame.dtype not in (np.uint8, np.uint16):  # what the node takes
                    raise InputError(
                        f'--image {args.image} is a {frame.dtype} image; expected an 8- or '
                        f'16-bit camera frame'
                    )
                if frame.ndim == 3:
                    frame = cv2.cvtColor(frame[..., :3], cv2.COLOR_BGR2RGB)
            else:
                index = 0 if args.frame is None else args.frame
                frame = frame_from_bag(args.bag, args.topic, index)
            height, width = frame.shape[:2]
        keep = draw_mask(
            width, height,
            start=start,
            rects=args.rect,
            polygons=[_parse_polygon(corners) for corners in args.polygon],
            below=args.below,
            above=args.above,
        )
        if not keep.any():
            raise ConfigError('the mask would ignore every pixel; the node would judge nothing')
        preview_path = args.preview
        if preview_path is None and frame is not None:
            preview_path = args.out.with_name(f'{args.out.stem}_preview.png')
        # The start mask may be the output itself: --overwrite says so.
        for path in (args.out, preview_path):
            # a folder is not replaced by --overwrite either: check_output_file names it
            if (path is not None and path.exists() and not path.is_dir()
                    and not args.overwrite):
                raise ConfigError(f'{path} exists already; use --overwrite to replace it')
        if preview_path is not None and frame is None:
            raise ConfigError('--preview needs a frame to draw on: --image or --bag')
        check_output_file(args.out, 'out')
        if preview_path is not None:
            check_output_file(preview_path, '--preview')
        # The preview is drawn before the mask is written: a frame it fails on writes nothing.
        shaded = None if frame is None else preview(frame, keep)
        _write_atomically(args.out, np.where(keep, 255, 0).astype(np.uint8))
        if preview_path is not None and shaded is not None:
            _write_atomically(preview_path, shaded)
    except CVAError as err:
        print(f'cva-mask: error: {err}', file=sys.stderr)
        return 2
    print(f'{args.out}: {summary(keep)}')
    if preview_path is not None:
        print(f'preview: {preview_path}')
    else:
        stale = args.out.with_name(f'{args.out.stem}_preview.png')
        if stale.exists():
            # An earlier run's preview of this mask, which no longer shows it.
            print(f'cva-mask: note: {stale} still shows the previous mask; give --image or '
                  '--bag to draw it again', file=sys.stderr)
    print(f'use it with: --ros-args -p mask_path:={args.out.resolve()}  '
          f'(cva-bag-replay --mask {args.out})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
