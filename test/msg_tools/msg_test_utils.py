"""Shared helpers of the msg_tools tests: tiny data sets on disk, hand-made bags, bag reading."""

from __future__ import annotations

from collections.abc import Sequence
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cva_confidence_ros.datasets.io import write_pfm
from cva_confidence_ros.pointcloud import StereoGeometry
from msg_tools.bagio import OutputBag
from msg_tools.convert import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DISPARITY_IMAGE,
    IMAGE,
    camera_info_msgs,
    disparity_to_msg,
    image_to_msg,
    jazzy_typestore,
)

MAX_DISPARITY = 16
START_NS = 1_700_000_000 * 10**9
# Two sizes, so a bag holds frames of different sizes as the tool must allow.
SIZES = ((40, 56), (36, 48), (40, 56))
DOFFS = 1.5


def domain_id() -> int:
    """A ROS domain for the live tests, from the pid; apart from the node tests' 101–220."""
    return 1 + os.getpid() % 90


def synthetic_samples(count: int = 2, first_seed: int = 3) -> list[Any]:
    """Tiny synthetic pairs (``datasets.synthetic``) with exact, dense ground truth."""
    from cva_confidence_ros.datasets.synthetic import synthetic_pair

    return [
        synthetic_pair(first_seed + i, *SIZES[i % len(SIZES)], max_disparity=MAX_DISPARITY)
        for i in range(count)
    ]


def write_middlebury_root(
    root: Path, samples: Sequence[Any], doffs: float = DOFFS, calib: bool = True
) -> Path:
    """Write samples in the MiddEval3 layout (``trainingQ/<Scene>/im0.png, im1.png,
    disp0GT.pfm, calib.txt``) so that they come back through the data set loader."""
    for index, sample in enumerate(samples):
        folder = root / 'trainingQ' / f'Scene{index}'
        folder.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / 'im0.png'), cv2.cvtColor(sample.left, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / 'im1.png'), cv2.cvtColor(sample.right, cv2.COLOR_RGB2BGR))
        gt = np.where(np.isfinite(sample.disparity), sample.disparity, np.inf)
        write_pfm(folder / 'disp0GT.pfm', gt.astype(np.float32))
        if calib:
            c = sample.calib
            height, width = sample.disparity.shape
            (folder / 'calib.txt').write_text(
                f'cam0=[{c.fx} 0 {c.cx}; 0 {c.fy} {c.cy}; 0 0 1]\n'
                f'cam1=[{c.fx} 0 {c.cx + doffs}; 0 {c.fy} {c.cy}; 0 0 1]\n'
                f'doffs={doffs}\nbaseline={1000 * c.baseline}\nwidth={width}\n'
                f'height={height}\nndisp={MAX_DISPARITY}\n'
            )
    return root


def dataset_bag(tmp_path: Path, storage: str = 'mcap', count: int = 2, *extra: str) -> Path:
    """A bag written by ``cva-bag-from-dataset`` from tiny Middlebury-layout scenes."""
    from msg_tools.bag_from_dataset import main

    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(count))
    bag = tmp_path / f'input_{storage}'
    code = main([
        '--data-root', str(root), '--dataset', 'middlebury2014', '--out', str(bag),
        '--storage', storage, *extra,
    ])
    assert code == 0
    return bag


def read_bag(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Topic → [(bag timestamp, deserialised message)] of every message, with ``rosbags``."""
    from rosbags.rosbag2 import Reader

    store = jazzy_typestore()
    out: dict[str, list[tuple[int, Any]]] = {}
    with Reader(path) as reader:
        for conn, timestamp, data in reader.messages():
            out.setdefault(conn.topic, []).append(
                (timestamp, store.deserialize_cdr(data, conn.msgtype))
            )
    return out


def textured_pair(height: int, width: int, shift: int, seed: int) -> tuple[np.ndarray, ...]:
    """Random texture seen with a constant disparity: left[y, x] = right[y, x − shift]."""
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 256, size=(height, width + shift), dtype=np.uint8)
    return texture[:, :width].copy(), texture[:, shift : shift + width].copy()


def write_stereo_bag(
    path: Path,
    frames: Sequence[dict[str, Any]],
    *,
    prefix: str = '',
    ground_truth: bool = True,
    storage: str = 'mcap',
    skip_topics: Sequence[str] = (),
    geometry: StereoGeometry | None = None,
) -> Path:
    """A hand-made stereo bag for fault cases.

    Each frame dict may hold ``left``/``right`` (uint8 arrays), ``shift`` (true disparity),
    ``stamp`` (ns, default ``START_NS`` + index × 0.1 s), ``stamp_right`` (ns, default the
    left stamp), ``encoding`` (forced on both images), ``info_size`` ((width, height) written
    into the camera infos), ``gt`` (a float32 ground-truth array instead of the true shift),
    ``gt_bytes`` (the ground truth's image data cut to this many bytes), ``gt_lag`` (the
    ground truth logged this many ns after its images, as a ground-truth node with latency
    does), ``no_gt`` (True: no ground truth for this frame), ``transport``
    (``'png'`` or ``'jpeg'``: the images as ``sensor_msgs/CompressedImage`` on
    ``<image topic>/compressed``, as image_transport's compressed plugin writes them),
    ``compressed_data`` (bytes written as the left image's compressed data instead),
    ``gt_scale`` (the ground truth's ``DisparityImage`` written with the geometry scaled by
    this factor, as for a ``gt`` array of that resolution: its values are d + Δ·factor),
    ``logged`` (the bag time of the frame's messages, ns; default its stamp: header stamps
    that jump back in a bag whose times go on).

    ``geometry`` is the stereo geometry of the camera infos (default: f = 50 px, cx = 20,
    cy = 15, no Δ: cx_right = cx).
    """
    store = jazzy_typestore()
    geometry = geometry or StereoGeometry(
        fx=50.0, fy=50.0, cx=20.0, cy=15.0, cx_right=20.0, baseline=0.1
    )
    with OutputBag(path, storage, store) as bag:
        for index, frame in enumerate(frames):
            stamp = frame.get('stamp', START_NS + index * 100_000_000)
            stamp_right = frame.get('stamp_right', stamp)
            shift = frame.get('shift', 4)
            left, right = frame.get('left'), frame.get('right')
            if left is None:
                left, right = textured_pair(30, 40, shift, index)
            height, width = left.shape[:2]
            info_w, info_h = frame.get('info_size', (width, height))
            left_info, _ = camera_info_msgs(geometry, info_w, info_h, stamp, ('l', 'r'), store)
            _, right_info = camera_info_msgs(
                geometry, info_w, info_h, stamp_right, ('l', 'r'), store
            )
            left_msg = image_to_msg(left, stamp, 'l', store)
            right_msg = image_to_msg(right, stamp_right, 'r', store)
            if 'encoding' in frame:
                left_msg.encoding = right_msg.encoding = frame['encoding']
            image_topic, image_type = 'image_rect', IMAGE
            if 'transport' in frame:
                image_topic, image_type = 'image_rect/compressed', COMPRESSED_IMAGE
                left_msg, right_msg = (
                    _compressed(array, msg, frame['transport'], store)
                    for array, msg in ((left, left_msg), (right, right_msg))
                )
                if 'compressed_data' in frame:
                    left_msg.data = np.frombuffer(frame['compressed_data'], np.uint8)
            gt = np.full((height, width), float(shift), np.float32)
            gt[:, :shift] = np.nan
            gt = frame.get('gt', gt)
            logged = frame.get('logged', stamp)
            messages = [
                ('left/camera_info', CAMERA_INFO, left_info, logged),
                ('right/camera_info', CAMERA_INFO, right_info, logged),
                (f'left/{image_topic}', image_type, left_msg, logged),
                (f'right/{image_topic}', image_type, right_msg, logged),
            ]
            if ground_truth and not frame.get('no_gt', False):
                gt_geometry = geometry.scaled(frame['gt_scale']) if 'gt_scale' in frame \
                    else geometry
                gt_msg = disparity_to_msg(gt, stamp, 'l', gt_geometry, typestore=store)
                if 'gt_bytes' in frame:
                    gt_msg.image.data = gt_msg.image.data[: frame['gt_bytes']]
                messages.append(('ground_truth/disparity', DISPARITY_IMAGE, gt_msg,
                                 logged + frame.get('gt_lag', 0)))
            for topic, msgtype, message, timestamp in messages:
                if topic in skip_topics:
                    continue
                bag.write(f'{prefix}/{topic}', msgtype, message, timestamp)
    return path


def _compressed(array: np.ndarray, raw: Any, transport: str, store: Any) -> Any:
    """The CompressedImage image_transport would publish for ``raw`` (mono8 or rgb8)."""
    encoding = raw.encoding
    pixels = cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 else array
    ok, data = cv2.imencode(f'.{"jpg" if transport == "jpeg" else "png"}', pixels)
    assert ok
    target = ' bgr8' if transport == 'jpeg' and array.ndim == 3 else ''
    return store.types[COMPRESSED_IMAGE](
        header=raw.header,
        format=f'{encoding}; {transport} compressed{target}',
        data=data.reshape(-1),
    )


def write_topics_without_messages(path: Path, topics: dict[str, str]) -> Path:
    """A bag that declares ``topics`` (name → type) but holds no message on them, as
    ``ros2 bag record`` leaves one that saw the topics advertised and nothing published."""
    from rosbags.rosbag2 import Writer

    store = jazzy_typestore()
    writer = Writer(path, version=8)
    writer.open()
    for topic, msgtype in topics.items():
        writer.add_connection(topic, msgtype, typestore=store)
    writer.close()
    return path


def _mcap_message_records(data: bytes) -> list[int]:
    """Offsets of the message records (opcode 0x05) inside the uncompressed chunks."""
    offsets = []
    position = 8  # after the magic
    while position + 9 <= len(data):
        opcode = data[position]
        length = int.from_bytes(data[position + 1 : position + 9], 'little')
        if opcode == 0x06:  # chunk: start, end, uncompressed size, crc, compression, records
            field = position + 9 + 8 + 8 + 8 + 4
            compression = int.from_bytes(data[field : field + 4], 'little')
            field += 4 + compression
            size = int.from_bytes(data[field : field + 8], 'little')
            record = field + 8
            while record < field + 8 + size:
                if data[record] == 0x05:
                    offsets.append(record)
                record += 9 + int.from_bytes(data[record + 1 : record + 9], 'little')
        elif opcode == 0x0F:  # footer
            break
        position += 9 + length
    return offsets


def break_storage(bag: Path) -> int:
    """Damage a bag's storage file so that it opens but fails while its messages are read.

    MCAP: a message record in the middle of the first chunk gets the length 2**64 − 1 (the
    reader overflows seeking past it). sqlite3: the overflow-page pointer of one page in the
    second half of the file becomes 0xffffffff, the first such page that ``rosbags`` fails on
    after some messages (SQLite reports the file as malformed).

    Returns:
        The number of messages ``rosbags`` reads before the failure.
    """
    from rosbags.rosbag2 import Reader

    def read_count() -> tuple[int, bool]:
        count = 0
        try:
            with Reader(bag) as reader:
                for _ in reader.messages():
                    count += 1
        except Exception:  # noqa: BLE001  (whatever the damage makes the library raise)
            return count, True
        return count, False

    [storage] = [p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3')]
    original = storage.read_bytes()
    if storage.suffix == '.mcap':
        records = _mcap_message_records(original)
        damaged = bytearray(original)
        middle = records[len(records) // 2]
        damaged[middle + 1 : middle + 9] = b'\xff' * 8
        storage.write_bytes(damaged)
        count, failed = read_count()
        assert failed
        return count
    page_size = 4096
    for page in range(len(original) // page_size // 2, len(original) // page_size):
        damaged = bytearray(original)
        damaged[page * page_size : page * page_size + 4] = b'\xff' * 4
        storage.write_bytes(damaged)
        count, failed = read_count()
        if failed and count > 0:
            return count
    raise AssertionError(f'no page of {storage} fails part-way when damaged')


def live_options(tmp_path: Path, bag: Path, *extra: str) -> Any:
    """``cva-bag-replay BAG --mode live`` options for the recorder tests: PKRN at D = 16 on
    the CPU, outputs under ``tmp_path``, a 1 s drain timeout."""
    from msg_tools.bag_replay import build_parser, options_from_args

    return options_from_args(build_parser().parse_args([
        str(bag), '--mode', 'live', '--out', str(tmp_path / 'out'),
        '--report', str(tmp_path / 'report'), '--matcher', 'census_bm',
        '--confidence-method', 'pkrn', '--device', 'cpu', '--max-disparity', str(MAX_DISPARITY),
        '--drain-timeout', '1', *extra,
    ]))


def truth_session(tmp_path: Path, **session: Any) -> Any:
    """A replay session with ground truth (PKRN, D = MAX_DISPARITY), used without its output
    bag or report writer; ``session``: further ``ReplaySession`` arguments."""
    from cva_confidence_ros.pipeline import PipelineConfig
    from msg_tools.replay import ReplayOptions, ReplaySession, TopicPlan

    options = ReplayOptions(
        bag=tmp_path / 'in', out=tmp_path / 'out', report=tmp_path / 'report',
        pipeline=PipelineConfig(max_disparity=MAX_DISPARITY, confidence_method='pkrn'),
    )
    plan = TopicPlan(
        inputs=options.topics.inputs(), input_types={},
        ground_truth=options.topics.resolve('ground_truth'),
        ground_truth_type=DISPARITY_IMAGE, pairs_expected=0,
    )
    return ReplaySession(options, plan, lambda _: None, **session)


def replay_offline(bag: Path, tmp_path: Path, capsys: Any, *extra: str) -> tuple[int, str, dict]:
    """``cva-bag-replay`` offline with PKRN at D = MAX_DISPARITY and no plots: (exit code,
    stderr, report.json or {} when none was written); stderr holds no traceback."""
    import json

    from msg_tools.bag_replay import main

    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--max-plots', '0', *extra,
    ])  # fmt: skip
    captured = capsys.readouterr()
    assert 'Traceback' not in captured.err
    report = tmp_path / 'report' / 'report.json'
    return code, captured.err, json.loads(report.read_text()) if report.exists() else {}


#: The frames of the replay-session tests (no bag): size and geometry of their ground truth.
SESSION_SHAPE = (6, 8)
SESSION_GEOMETRY = StereoGeometry(fx=50.0, fy=50.0, cx=20.0, cy=15.0, cx_right=20.0,
                                  baseline=0.1)


def session_frame(index: int, stamp: int, value: float = 3.0) -> Any:
    """A processed frame for a replay session: disparity ``value`` everywhere, a random
    confidence (seeded by ``index``)."""
    from msg_tools.replay import FrameResult

    confidence = np.random.default_rng(index).random(SESSION_SHAPE).astype(np.float32)
    return FrameResult(
        frame=index, stamp_ns=stamp, disparity=np.full(SESSION_SHAPE, value, np.float32),
        confidence=confidence, kept=confidence > 0.5,
    )


def session_truth(stamp: int, value: float = 3.0) -> Any:
    """A ground-truth DisparityImage of ``value`` everywhere, stamped ``stamp``."""
    return disparity_to_msg(np.full(SESSION_SHAPE, value, np.float32), stamp, 'l',
                            SESSION_GEOMETRY, typestore=jazzy_typestore())
