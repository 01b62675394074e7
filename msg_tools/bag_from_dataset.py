"""``cva-bag-from-dataset``: write a stereo data set as a rosbag2, as a robot would record it.

Per frame (one scene of the data set), all with the same header stamp and bag timestamp:

* ``left/image_rect``, ``right/image_rect`` (sensor_msgs/Image, ``rgb8`` or ``mono8``),
* ``left/camera_info``, ``right/camera_info`` (sensor_msgs/CameraInfo, rectified: K, R = I,
  P with Tx = −fx·B on the right),
* ``ground_truth/disparity`` (stereo_msgs/DisparityImage, 32FC1, NaN where unknown).

Camera infos come from the data set's calibration where it has one (KITTI ``calib``,
Middlebury ``calib.txt``); ``--focal`` / ``--baseline`` override it, and without either a
pinhole with f = image width and B = 0.1 m is assumed (and said so). Frames are stamped
``--start-time + i / --rate``; every frame carries its own size. Bags are rosbag2 version 8
with ROS 2 Jazzy message definitions, MCAP by default, readable by ``ros2 bag info/play``.

Exit codes: 0 done, 2 bad input or a scene that cannot be read (one line on stderr), 130
interrupted by Ctrl-C, 143 by SIGTERM (the bag keeps the frames written). ``--overwrite``
also replaces the folder that a killed or disk-full run left without its ``metadata.yaml``.

Example::

    cva-bag-from-dataset --dataset motorcycle --out motorcycle_bag
    cva-bag-from-dataset --data-root data --dataset kitti2015 --out kitti_bag --rate 10
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from decimal import Decimal
import math
from pathlib import Path
import sys
from typing import Any

import numpy as np

from cva_confidence_ros.errors import (
    BagError,
    ConfigError,
    CVAError,
    interrupted_exit,
    sigterm_as_interrupt,
)
from cva_confidence_ros.pointcloud import StereoGeometry
from msg_tools.bagio import (
    BAG_VERSION,
    COMPRESSIONS,
    STORAGES,
    OutputBag,
    check_replaceable,
    check_topic_name,
)
from msg_tools.convert import (
    CAMERA_INFO,
    DISPARITY_IMAGE,
    IMAGE,
    camera_info_msgs,
    disparity_to_msg,
    image_to_msg,
    jazzy_typestore,
)
from msg_tools.progress import GracefulInterrupt

__all__ = ['BagSpec', 'DatasetBagSummary', 'main', 'sample_geometry', 'write_dataset_bag']

Logger = Callable[[str], None]

# Stamps start at a fixed instant by default, so the same data set always gives the same bag.
DEFAULT_START_TIME_S = 1_700_000_000.0
DEFAULT_BASELINE_M = 0.1
#: Header stamps (builtin_interfaces/Time) hold int32 seconds: the last one is in 2038.
MAX_STAMP_S = 2**31 - 1
_STAMP_LIMIT_NS = (MAX_STAMP_S + 1) * 1_000_000_000
#: One frame per nanosecond, the resolution of the stamps.
MAX_RATE_HZ = 1e9
# Topics of the images and camera infos, relative to the prefix.
_CAMERA_TOPICS = ('left/image_rect', 'right/image_rect', 'left/camera_info', 'right/camera_info')


#: Written on the first Ctrl-C: a loading scene can take a while, the run is not stuck.
STOPPING = '[cva-bag-from-dataset] Ctrl-C: stopping after this frame; the bag keeps it'


def _log_stderr(message: str) -> None:
    print(f'[cva-bag-from-dataset] {message}', file=sys.stderr, flush=True)


@dataclass(frozen=True)
class BagSpec:
    """How the data set is laid out in the bag.

    Attributes:
        storage: ``mcap`` or ``sqlite3``.
        compression: ``none``, ``file`` or ``message`` (zstd, as ``ros2 bag record`` does).
        rate_hz: Frames per second of the stamps (> 0, at most :data:`MAX_RATE_HZ`; low
            enough a rate puts the second frame past :data:`MAX_STAMP_S` and is refused).
        start_time_s: Stamp of the first frame, seconds since the epoch (0 to
            :data:`MAX_STAMP_S`).
        focal: Focal length in pixels overriding the data set's calibration (None = keep).
        baseline: Baseline in metres overriding the calibration (None = keep).
        topic_prefix: Namespace of every topic ('' = root), e.g. ``/stereo``; with the topic
            names it must make valid ROS 2 topic names (``bagio.check_topic_name``).
        left_frame: frame_id of the left camera (images, infos, ground truth); not starting
            with '/', which tf2 refuses.
        right_frame: frame_id of the right camera (the same).
        gt_topic: Topic of the ground truth, relative to the prefix.
    """

    storage: str = 'mcap'
    compression: str = 'none'
    rate_hz: float = 1.0
    start_time_s: float = DEFAULT_START_TIME_S
    focal: float | None = None
    baseline: float | None = None
    topic_prefix: str = ''
    left_frame: str = 'left_camera_optical_frame'
    right_frame: str = 'right_camera_optical_frame'
    gt_topic: str = 'ground_truth/disparity'

    def __post_init__(self) -> None:
        if self.storage not in STORAGES:
            raise ConfigError(f'storage must be one of {STORAGES}; got {self.storage!r}')
        if self.compression not in COMPRESSIONS:
            raise ConfigError(
                f'compression must be one of {COMPRESSIONS}; got {self.compression!r}'
            )
        if not (math.isfinite(self.rate_hz) and 0 < self.rate_hz <= MAX_RATE_HZ):
            raise ConfigError(
                f'rate must be a positive number of Hz, at most {MAX_RATE_HZ:g} (one frame per '
                f'ns); got {self.rate_hz}'
            )
        if not (math.isfinite(self.start_time_s) and 0 <= self.start_time_s <= MAX_STAMP_S):
            raise ConfigError(
                f'start time must be 0 to {MAX_STAMP_S} s (header stamps hold int32 seconds); '
                f'got {self.start_time_s}'
            )
        if self._raw_stamp_ns(1) >= _STAMP_LIMIT_NS:
            raise ConfigError(
                f'rate {self.rate_hz} Hz puts frame 1 at {self._raw_stamp_ns(1) / 1e9:.0f} s, '
                f'past the last header stamp ({MAX_STAMP_S} s, int32 seconds); raise the rate '
                f'or lower the start time'
            )
        if self.focal is not None and not self.focal > 0:
            raise ConfigError(f'focal must be > 0 pixels; got {self.focal}')
        if self.baseline is not None and not self.baseline > 0:
            raise ConfigError(f'baseline must be > 0 m; got {self.baseline}')
        if not self.left_frame or not self.right_frame:
            raise ConfigError('frame ids must not be empty')
        for side, frame in (('left', self.left_frame), ('right', self.right_frame)):
            if frame.startswith('/'):
                # tf2 refuses such a frame ('frame_ids cannot start with a /'): nothing the
                # node publishes in it could be placed.
                raise ConfigError(
                    f"{side} frame id must not start with '/' (tf2 refuses such frames); got "
                    f'{frame!r}'
                )
        prefix = self.topic_prefix.strip('/')
        if prefix:
            check_topic_name(f'/{prefix}', 'topic prefix')
        if not self.gt_topic.strip('/'):
            raise ConfigError(
                f'ground-truth topic must be a non-empty name; got {self.gt_topic!r}'
            )
        gt = check_topic_name(self.topic(self.gt_topic.strip('/')), 'ground-truth topic')
        if gt in {self.topic(name) for name in _CAMERA_TOPICS}:
            raise ConfigError(
                f'ground-truth topic {gt} is one of the image or camera-info topics; pick '
                f'another'
            )

    def topic(self, name: str) -> str:
        """Absolute topic of a relative ``name`` under :attr:`topic_prefix`."""
        prefix = self.topic_prefix.strip('/')
        return f'/{prefix}/{name}' if prefix else f'/{name}'

    def stamp_ns(self, index: int) -> int:
        """Header stamp of frame ``index`` in nanoseconds.

        Raises:
            ConfigError: The stamp lies past :data:`MAX_STAMP_S` (too many frames for the
                rate and start time).
        """
        stamp = self._raw_stamp_ns(index)
        if stamp >= _STAMP_LIMIT_NS:
            raise ConfigError(
                f'frame {index} would be stamped {stamp / 1e9:.0f} s, past the last header '
                f'stamp ({MAX_STAMP_S} s, int32 seconds); raise the rate, lower the start time '
                f'or write fewer frames'
            )
        return stamp

    def _raw_stamp_ns(self, index: int) -> int:
        # The start as it was written (repr: the shortest decimal of the float): in float
        # arithmetic 1700000000.999 s became 1700000000999000064 ns.
        start = Decimal(repr(float(self.start_time_s))) * 1_000_000_000
        return int(start.to_integral_value()) + int(round(index * 1e9 / self.rate_hz))


@dataclass
class DatasetBagSummary:
    """What was written: the bag, the number of frames, the scenes and topic counts;
    ``kept_old``: an old bag was to be replaced but no frame was written, so it is untouched."""

    path: Path
    frames: int = 0
    scenes: list[str] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    assumed_calibration: bool = False
    interrupted: bool = False
    kept_old: bool = False
    #: The exit status of an interrupted run: 130 Ctrl-C, 143 SIGTERM.
    interrupt_code: int = 130


def sample_geometry(sample: Any, spec: BagSpec) -> tuple[StereoGeometry, bool]:
    """Stereo geometry of one data-set sample.

    Args:
        sample: A ``datasets.StereoSample`` (``calib`` may be None).
        spec: ``focal`` / ``baseline`` there override the calibration.

    Returns:
        ``(geometry, assumed)``: ``assumed`` is True when a value had to be made up (no
        calibration and no override): f = image width, B = 0.1 m, principal point at the
        image centre.
    """
    height, width = np.asarray(sample.left).shape[:2]
    calib = getattr(sample, 'calib', None)
    assumed = False
    if calib is not None:
        fx, fy, cx, cy = (float(v) for v in (calib.fx, calib.fy, calib.cx, calib.cy))
        baseline = float(calib.baseline)
        doffs = float(getattr(calib, 'doffs', 0.0) or 0.0)
    else:
        fx = fy = float(width)
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        baseline = DEFAULT_BASELINE_M
        doffs = 0.0
        assumed = spec.focal is None or spec.baseline is None
    if spec.focal is not None:
        fy = fy * spec.focal / fx
        fx = float(spec.focal)
    if spec.baseline is not None:
        baseline = float(spec.baseline)
    return (
        StereoGeometry(fx=fx, fy=fy, cx=cx, cy=cy, cx_right=cx + doffs, baseline=baseline),
        assumed,
    )


def _assumed(spec: BagSpec) -> str:
    """What is made up for a sample without calibration, and the option that sets it."""
    parts = [] if spec.focal is not None else ['f = image width']
    options = [] if spec.focal is not None else ['--focal']
    if spec.baseline is None:
        parts.append(f'B = {DEFAULT_BASELINE_M} m')
        options.append('--baseline')
    return f'{", ".join(parts)} (set {"/".join(options)})'


def write_dataset_bag(
    samples: Iterable[Any],
    out: str | Path,
    spec: BagSpec | None = None,
    log: Logger = _log_stderr,
    overwrite: bool = False,
) -> DatasetBagSummary:
    """Write stereo samples into a new rosbag2.

    Args:
        samples: ``datasets.StereoSample`` objects (left/right uint8 (H, W[, 3]), disparity
            (H, W) float32 NaN = unknown, ``calib`` or None); each becomes one frame.
        out: Bag folder to create (must not exist unless ``overwrite``).
        spec: Layout (storage, rate, stamps, topics, frames); defaults if None.
        log: Receives one line per frame.
        overwrite: Replace an existing bag at ``out``; the new bag is written aside and takes
            the old one's place only once it holds a frame and the run did not fail
            (``bagio.OutputBag``).

    Returns:
        A :class:`DatasetBagSummary`. A Ctrl-C stops between frames; the bag is still
        finalised with the frames written so far (``interrupted`` is True). A run that wrote
        no frame leaves no bag of its own (an old one stays as it was).

    Raises:
        BagError: ``out`` exists (without ``overwrite``, or it is not a bag) or cannot be
            written.
        DataError, InputError: A sample that cannot be read or converted. The run failed: an
            old bag is left as it was, a new bag keeps the frames written before (none: no
            bag is left), and the message says which.
    """
    spec = spec or BagSpec()
    store = jazzy_typestore()
    summary = DatasetBagSummary(path=Path(out))
    topics = {
        'left': spec.topic('left/image_rect'),
        'right': spec.topic('right/image_rect'),
        'left_info': spec.topic('left/camera_info'),
        'right_info': spec.topic('right/camera_info'),
        'gt': spec.topic(spec.gt_topic.strip('/')),
    }
    # The notice goes to stderr whatever ``log`` is: it answers the person who pressed Ctrl-C.
    interrupts = GracefulInterrupt(notice=STOPPING)
    # A run that writes no frame (Ctrl-C before the first, no samples) leaves no empty bag.
    bag = OutputBag(
        out, spec.storage, store, spec.compression, overwrite=overwrite, keep_empty=False
    )
    with interrupts:
        bag.open()
        try:
            for index, sample in enumerate(samples):
                interrupts.check()
                geometry, assumed = sample_geometry(sample, spec)
                if assumed and not summary.assumed_calibration:
                    log(f'{sample.dataset}/{sample.scene} has no calibration: assuming '
                        f'{_assumed(spec)}')
                summary.assumed_calibration |= assumed
                messages = _frame_messages(sample, geometry, spec, index, store)
                stamp = spec.stamp_ns(index)
                with interrupts.critical():
                    for key, msgtype, message in messages:
                        bag.write(topics[key], msgtype, message, stamp)
                summary.frames += 1
                summary.scenes.append(f'{sample.dataset}/{sample.scene}')
                height, width = np.asarray(sample.left).shape[:2]
                log(f'frame {index}: {sample.dataset}/{sample.scene} {width}×{height} '
                    f'at {stamp / 1e9:.3f} s')
                interrupts.check()  # before the next scene is loaded, which takes a while
        except KeyboardInterrupt:
            summary.interrupted = True
            summary.interrupt_code = interrupts.exit_code
        except Exception as err:
            # A failed run replaces no old bag and leaves no empty one that a retry would have
            # to --overwrite; a new bag keeps the frames written, and the message says which.
            interrupts.closing()
            bag.close(failed=True)
            state = _failed_state(bag, out, summary.frames)
            if isinstance(err, CVAError) and state:
                raise type(err)(f'{err}; {state}') from None
            raise
        finally:
            interrupts.closing()
            bag.close()
    summary.counts = dict(bag.counts)
    summary.kept_old = bag.kept_old
    return summary


def _failed_state(bag: OutputBag, out: str | Path, frames: int) -> str:
    """What a failed run left at ``out``, for its error message ('' when the error says it)."""
    if bag.kept_old:
        dropped = f' (the {frames} frames written were dropped)' if frames else ''
        return f'the existing bag {out} was left as it was{dropped}'
    if bag.dropped_empty:
        return f'no bag was written at {out}'
    if bag.replacing or bag.lost:
        # The new bag could not be written, or its storage lost every frame (sqlite3 on a
        # full disk): the error says what was kept.
        return ''
    return f'{out} holds the {frames} frames written before it'


def _frame_messages(
    sample: Any, geometry: StereoGeometry, spec: BagSpec, index: int, store: Any
) -> list[tuple[str, str, Any]]:
    stamp = spec.stamp_ns(index)
    left = np.asarray(sample.left)
    right = np.asarray(sample.right)
    height, width = left.shape[:2]
    left_info, right_info = camera_info_msgs(
        geometry, width, height, stamp, (spec.left_frame, spec.right_frame), store
    )
    gt = np.asarray(sample.disparity, dtype=np.float32)
    # Unknown is NaN in the bag: +inf (how Middlebury's PFMs and ``read_pfm`` mark it) would be
    # a valid disparity, a depth of 0 m, to any other reader.
    gt = np.where(np.isfinite(gt), gt, np.float32(np.nan))
    return [
        ('left_info', CAMERA_INFO, left_info),
        ('right_info', CAMERA_INFO, right_info),
        ('left', IMAGE, image_to_msg(left, stamp, spec.left_frame, store)),
        ('right', IMAGE, image_to_msg(right, stamp, spec.right_frame, store)),
        (
            'gt',
            DISPARITY_IMAGE,
            disparity_to_msg(gt, stamp, spec.left_frame, geometry, delta_d=0.0, typestore=store),
        ),
    ]


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``cva-bag-from-dataset``."""
    parser = argparse.ArgumentParser(
        prog='cva-bag-from-dataset',
        description='Write a stereo data set (images, camera infos, ground-truth disparity) '
        'as a rosbag2 (MCAP or sqlite3) readable by ros2 bag and rosbags.',
        epilog='Exit codes: 0 done, 2 bad input or a scene that cannot be read (one line on '
        'stderr: an old bag stays as it was, a new one keeps the frames before it), 130 '
        'interrupted by Ctrl-C, 143 by SIGTERM (the bag keeps the frames written).',
    )
    parser.add_argument('--data-root', type=Path, default=None,
                        help='folder holding the data set (not needed for motorcycle)')
    parser.add_argument('--dataset', required=True,
                        help='data set name: kitti2012, kitti2015, middlebury2014, '
                        'middlebury2003, middlebury2001, middlebury2005, middlebury2006, '
                        'eth3d, flyingthings3d, sceneflow_extra, tartanair, motorcycle, '
                        'stereo_folder (your own pairs: <scene>/left.png, right.png, '
                        'disparity.pfm|npy|png; calib.txt for the camera infos)')
    parser.add_argument('--split', default=None, help='data set split (e.g. trainingQ)')
    parser.add_argument('--out', type=Path, required=True, help='bag folder to create')
    parser.add_argument('--storage', choices=STORAGES, default='mcap',
                        help='storage plugin (default mcap)')
    parser.add_argument('--compression', choices=COMPRESSIONS, default='none',
                        help='zstd compression mode (default none)')
    parser.add_argument('--rate', type=float, default=1.0, help='frames per second (default 1)')
    parser.add_argument('--max-frames', type=int, default=None, help='write at most N scenes')
    parser.add_argument('--focal', type=float, default=None,
                        help='focal length in pixels (overrides the calibration)')
    parser.add_argument('--baseline', type=float, default=None,
                        help='baseline in metres (overrides the calibration)')
    parser.add_argument('--topic-prefix', default='', help='namespace of all topics, e.g. /stereo')
    parser.add_argument('--start-time', type=float, default=DEFAULT_START_TIME_S,
                        help='stamp of the first frame, seconds since the epoch')
    parser.add_argument('--left-frame', default='left_camera_optical_frame',
                        help='frame_id of the left camera')
    parser.add_argument('--right-frame', default='right_camera_optical_frame',
                        help='frame_id of the right camera')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an existing bag (also the folder a killed or disk-full '
                        'run left without its metadata.yaml)')
    return parser


def _run(args: argparse.Namespace) -> tuple[BagSpec, DatasetBagSummary]:
    """Check the options, load the data set and write the bag (``main`` without its exit
    codes)."""
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f'--max-frames must be >= 1; got {args.max_frames}')
    spec = BagSpec(
        storage=args.storage,
        compression=args.compression,
        rate_hz=args.rate,
        start_time_s=args.start_time,
        focal=args.focal,
        baseline=args.baseline,
        topic_prefix=args.topic_prefix,
        left_frame=args.left_frame,
        right_frame=args.right_frame,
    )
    from cva_confidence_ros.datasets import DATASETS, load_dataset, skipped_notice

    DATASETS.get(args.dataset)  # a misspelt name is that, not a missing --data-root
    root = args.data_root
    if root is None and args.dataset != 'motorcycle':
        raise ConfigError(f'--data-root is needed for data set {args.dataset!r}')
    # Before any work: an existing --out needs --overwrite and must be a bag.
    if args.out.exists() or args.out.is_symlink():
        if not args.overwrite:
            raise BagError(
                f'output bag {args.out} exists already; use --overwrite to replace it, or '
                f'pick another'
            )
        check_replaceable(args.out)
    notice = skipped_notice(args.dataset, root, split=args.split)
    if notice:
        _log_stderr(notice)  # a partial download: fewer frames than scenes in the folder
    samples = load_dataset(args.dataset, root, split=args.split, max_scenes=args.max_frames)
    return spec, write_dataset_bag(samples, args.out, spec, overwrite=args.overwrite)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cva-bag-from-dataset``; returns the exit code (0 done, 2 bad input or a
    scene that cannot be read, 130 Ctrl-C, 143 SIGTERM)."""
    args = build_parser().parse_args(argv)
    # Until write_dataset_bag's own handlers are set (a data set still loading), a SIGTERM took
    # its default action: 143 without a word. ``terminated`` tells it from Ctrl-C.
    with sigterm_as_interrupt() as terminated:
        try:
            spec, summary = _run(args)
        except CVAError as err:
            print(f'cva-bag-from-dataset: error: {err}', file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return interrupted_exit(
                'cva-bag-from-dataset', terminated, ' before the bag was created'
            )
    if summary.frames == 0:
        state = (
            f'the existing bag {args.out} was left as it was' if summary.kept_old
            else f'no bag was written at {args.out}'
        )
        if summary.interrupted:
            print(f'cva-bag-from-dataset: interrupted before the first frame was written; '
                  f'{state}', file=sys.stderr)
            return summary.interrupt_code
        print(f'cva-bag-from-dataset: error: data set {args.dataset!r} yielded no frames; '
              f'{state}', file=sys.stderr)
        return 2
    state = 'interrupted: ' if summary.interrupted else ''
    print(f'{state}wrote {summary.frames} frames to {summary.path} ({spec.storage}, rosbag2 '
          f'version {BAG_VERSION}, topics: {", ".join(sorted(summary.counts))})')
    return summary.interrupt_code if summary.interrupted else 0


if __name__ == '__main__':
    sys.exit(main())
