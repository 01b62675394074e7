"""The replay engine of ``cva-bag-replay``: options, topic plan, output messages, and the
offline mode (the live mode is :mod:`msg_tools.live`; both share :class:`ReplaySession`).

Offline mode reads the bag in time order, pairs left/right images and camera infos by stamp
with the node's synchroniser (``sync.StampSynchronizer``), runs the node's pipeline
(``pipeline.StereoPipeline``) on every pair as fast as it can, writes what the node would
publish into an output bag (header stamps of the input, bag timestamps of the input left
image) and scores each frame against the ground truth topic, when the bag has one.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Callable
import contextlib
from dataclasses import asdict, dataclass, field
import importlib
import math
from pathlib import Path
from typing import Any

import numpy as np

from cva_confidence_ros.errors import BagError, ConfigError, CVAError, InputError, from_interrupt
from cva_confidence_ros.outputs import check_output_dir
from cva_confidence_ros.pipeline import PipelineConfig, PipelineResult
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.scan import ScanConfig
from cva_confidence_ros.sync import DEFAULT_KEYS
from msg_tools.bagio import (
    STORAGES,
    InputBag,
    OutputBag,
    check_replaceable,
    check_topic_name,
    staging_folder,
)
from msg_tools.convert import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DISPARITY_IMAGE,
    IMAGE,
    LASER_SCAN,
    POINT_CLOUD2,
    disparity_from_msg,
    jazzy_typestore,
    stamp_to_ns,
)
from msg_tools.progress import GracefulInterrupt, Progress, print_above
from msg_tools.scoring import (
    FrameScore,
    ReplayReport,
    ReportFolderLock,
    ReportWriter,
    check_report_folder,
    clear_report,
    score_frame,
)

__all__ = [
    'COMPRESSED_OUTPUTS',
    'CompressionConfig',
    'FrameResult',
    'GT_WAIT_FRAMES',
    'Logger',
    'NodeOutputs',
    'ReplayOptions',
    'ReplayOutcome',
    'ReplaySession',
    'TopicNames',
    'TopicPlan',
    'TRUTH_JUMP_NS',
    'check_output_bag_folder',
    'log_stderr',
    'make_synchronizer',
    'node_outputs',
    'output_left_image',
    'plan_topics',
    'preload',
    'run_offline',
    'stereo_inputs',
]

Logger = Callable[[str], None]

INPUT_KEYS = DEFAULT_KEYS
# Images raw or as image_transport's compressed (JPEG / PNG); decoded by the node's decoder.
_INPUT_TYPES = {
    'left': (IMAGE, COMPRESSED_IMAGE),
    'right': (IMAGE, COMPRESSED_IMAGE),
    'left_info': (CAMERA_INFO,),
    'right_info': (CAMERA_INFO,),
}
GT_TYPES = (DISPARITY_IMAGE, IMAGE)
# Skips are counted always but logged only this often, so a bag of bad frames stays readable.
_MAX_SKIP_LOGS = 20
# The same for unpaired input messages, and for unscored frames (per reason).
_MAX_UNPAIRED_LOGS = 10
_MAX_UNSCORED_LOGS = 3
# Readable names of the synchroniser keys.
_KEY_NAMES = {
    'left': 'left image', 'right': 'right image', 'left_info': 'left camera info',
    'right_info': 'right camera info',
}
#: The line a first Ctrl-C prints (a run stops between frames, not inside one).
STOPPING = '[cva-bag-replay] Ctrl-C: stopping after this frame'
#: The outputs that also go as ``image_transport``'s compressed transports, as the node
#: advertises them: output name → (the raw output it encodes, the transport's sub-topic).
COMPRESSED_OUTPUTS = {
    'depth_compressed': ('depth', 'compressedDepth'),
    'overlay_compressed': ('overlay', 'compressed'),
}
# Longest span rosbag2 timestamps (int64 nanoseconds) can express, in seconds.
_MAX_SPAN_S = (2**63 - 1) / 1e9
#: Most processed frames that wait for their ground truth at once, and most ground-truth
#: messages that wait for their frame. A frame stops waiting as soon as ground truth of a stamp
#: :data:`TRUTH_JUMP_NS` or more later is read (the topic comes in stamp order but for messages
#: a little out of order, so its own cannot come any more); this bound is for ground truth that
#: lags its images (a ground-truth node's latency) and keeps the memory bounded. It does not
#: depend on --queue-size, the synchroniser's setting.
GT_WAIT_FRAMES = 100
# Stamps remembered to say why a frame went unscored (plain integers: cheap to keep).
_MAX_REMEMBERED = 1000
#: How far back a ground-truth stamp must go to be a jump back at once (the synchroniser's
#: ``min_jump_ns`` default); a shorter step back is one message out of order (a ground-truth
#: node whose latency varies) unless the next one goes back too (a short loop).
TRUTH_JUMP_NS = 1_000_000_000
#: Stamps of ground-truth messages that matched no processed frame listed in the report and
#: the closing line (all are counted).
MAX_LISTED_UNMATCHED_TRUTH = 5


def log_stderr(message: str) -> None:
    """Print one ``[cva-bag-replay]`` line on stderr."""
    # Above a progress line on a terminal, not glued to its end.
    print_above(f'[cva-bag-replay] {message}')


@dataclass(frozen=True)
class TopicNames:
    """Topic names of the replay; relative names are resolved under ``prefix``.

    Defaults are stereo_image_proc's names. A bag recorded under a camera namespace (e.g.
    ``/stereo/left/image_rect``) needs only ``prefix='/stereo'``; a name given absolute (with
    a leading ``/``) is used as it is. Every resolved name must be a valid ROS 2 topic name
    (``bagio.check_topic_name``), or the node and ``ros2 bag play`` could not use it.

    Attributes:
        prefix: Namespace of every relative name ('' = root).
        left, right: Rectified images (sensor_msgs/Image, or CompressedImage: JPEG / PNG).
        left_info, right_info: Camera infos (sensor_msgs/CameraInfo).
        ground_truth: Ground-truth disparity (stereo_msgs/DisparityImage or 32FC1 Image).
        disparity, confidence, points, disparity_filtered, depth, overlay, scan, camera_info:
            What the node publishes (``camera_info``: the left camera at the output
            resolution). ``depth`` and ``overlay`` also name their compressed transports,
            ``<depth>/compressedDepth`` and ``<overlay>/compressed`` (:meth:`outputs`).
    """

    prefix: str = ''
    left: str = 'left/image_rect'
    right: str = 'right/image_rect'
    left_info: str = 'left/camera_info'
    right_info: str = 'right/camera_info'
    ground_truth: str = 'ground_truth/disparity'
    disparity: str = 'disparity'
    confidence: str = 'confidence'
    points: str = 'points2'
    disparity_filtered: str = 'disparity_filtered'
    depth: str = 'depth'
    overlay: str = 'confidence_overlay'
    scan: str = 'scan'
    camera_info: str = 'camera_info'

    def __post_init__(self) -> None:
        prefix = str(self.prefix).strip('/')
        if prefix:
            try:
                check_topic_name(f'/{prefix}', 'topic prefix')
            except ConfigError as err:
                raise ConfigError(str(err), 'prefix') from None
        for name, value in asdict(self).items():
            if name == 'prefix':
                continue
            if not str(value).strip('/'):
                raise ConfigError(f'topic {name} must be a non-empty name; got {value!r}', name)
            try:
                check_topic_name(self.resolve(name), f'topic {name}')
            except ConfigError as err:
                raise ConfigError(str(err), name) from None
        # The replay tells its inputs apart by topic: two on one topic would leave one of
        # them without messages (every frame unpaired, or the images read as ground truth).
        named: dict[str, str] = {}
        for name in (*INPUT_KEYS, 'ground_truth'):
            topic = self.resolve(name)
            if topic in named:
                raise ConfigError(
                    f'topics {named[topic]} and {name} are both {topic!r}; every input (and '
                    f'the ground truth) needs a topic of its own'
                )
            named[topic] = name

    def resolve(self, name: str) -> str:
        """The absolute topic name of ``name`` (which may be one of the attribute names)."""
        value = getattr(self, name, name)
        if value.startswith('/'):
            return value
        prefix = '/' + self.prefix.strip('/') if self.prefix.strip('/') else ''
        return f'{prefix}/{value.strip("/")}'

    def inputs(self) -> dict[str, str]:
        """Synchroniser key → absolute input topic."""
        return {key: self.resolve(key) for key in INPUT_KEYS}

    def outputs(self) -> dict[str, str]:
        """Output name → absolute topic, for what the node publishes.

        Besides the raw outputs, ``depth_compressed`` and ``overlay_compressed``
        (:data:`COMPRESSED_OUTPUTS`): image_transport's sub-topics of the resolved ``depth``
        and ``overlay``, as the node and ``image_transport`` name them.
        """
        names = (
            'disparity', 'confidence', 'points', 'disparity_filtered', 'depth', 'overlay', 'scan',
            'camera_info',
        )
        topics = {name: self.resolve(name) for name in names}
        for name, (raw, transport) in COMPRESSED_OUTPUTS.items():
            topics[name] = f'{topics[raw]}/{transport}'
        return topics


@dataclass(frozen=True)
class CompressionConfig:
    """How ``--compressed`` encodes ``depth`` and ``confidence_overlay``: the node's
    parameters of the same names (:class:`cva_confidence_ros.ros.params.NodeConfig`), checked
    as the node checks them (their declared ranges, then ``NodeConfig``'s own checks).

    Attributes:
        overlay_jpeg_quality: JPEG quality (1–100) of ``confidence_overlay/compressed``.
        compressed_depth_max: Largest depth on ``depth/compressedDepth``, metres; deeper
            pixels travel as no depth.
        compressed_depth_quantization: Inverse-depth quantisation ``q`` of a 32FC1
            ``depth/compressedDepth``: a depth z comes back within about z² / (q·(q + 1)).
        compressed_depth_png_level: zlib level (0–9) of the ``depth/compressedDepth`` PNG.

    Raises:
        ConfigError: A value the node would refuse (naming the parameter, also in ``fields``).
    """

    # The node's defaults (NodeConfig's; a test keeps them equal without importing rclpy here).
    overlay_jpeg_quality: int = 95
    compressed_depth_max: float = 10.0
    compressed_depth_quantization: float = 100.0
    compressed_depth_png_level: int = 3

    def __post_init__(self) -> None:
        from cva_confidence_ros.ros.params import NODE_PARAMETERS, NodeConfig, double_value

        specs = {spec.name: spec for spec in NODE_PARAMETERS}
        for name, value in asdict(self).items():
            spec = specs[name]
            low, high = spec.low, spec.high
            assert low is not None and high is not None  # the four are declared with a range
            if isinstance(spec.default, float):
                # As the node takes a double parameter: an integer is that number; NaN and
                # values outside the declared range are refused.
                value = double_value(name, value, low, high)
            elif isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                # rclpy refuses these by the descriptor's integer range.
                raise ConfigError(
                    f'{name} must be an integer in [{low:g}, {high:g}]; got {value!r}', name
                )
            object.__setattr__(self, name, value)
        NodeConfig(**asdict(self))


@dataclass(frozen=True)
class ReplayOptions:
    """Everything one replay run needs (built by the CLI; the node parameters are
    ``pipeline`` plus the sync and points options, under the node's names).

    Attributes:
        bag: Input bag (folder, ``.mcap`` or ``.db3``).
        out: Output bag folder to create; it must neither be nor hold nor lie in the input.
        report: Report folder; not the output bag or the input bag, nor inside either.
        pipeline: The node's processing settings.
        topics: Topic names.
        gt_required: The ground-truth topic was asked for explicitly, so it must exist.
        mode: ``offline`` or ``live``.
        storage: Output storage, ``mcap`` or ``sqlite3``.
        approximate_sync: Pair by approximate stamps (within ``sync_tolerance_s``).
        sync_tolerance_s: Largest stamp spread of one pair in approximate mode, seconds.
        queue_size: Messages held per input while waiting for a match.
        max_pixels: Score a random subset of this many ground-truth pixels per frame.
        seed: Seed of that subset (>= 0).
        max_plots: Frames that get a confidence-map and ROC PNG.
        publish_points: Write ``points2``.
        points_organized: Organised (H×W, NaN for dropped points) or dense cloud.
        points_confidence: ``points2`` holds every triangulated point with its confidence
            (the node's ``points_confidence``) instead of the kept ones only.
        publish_depth: Write ``depth`` (the depth of the kept pixels, REP 118).
        depth_encoding: ``32FC1`` (metres) or ``16UC1`` (millimetres), the node's parameter.
        publish_overlay: Write ``confidence_overlay`` (rgb8, the kept pixels tinted by
            confidence over the scene; the node computes it only for a subscriber).
        compressed: Write ``depth`` and ``confidence_overlay`` as image_transport's
            ``depth/compressedDepth`` and ``confidence_overlay/compressed``
            (``sensor_msgs/CompressedImage``, encoded with these settings as the node
            encodes them) instead of the raw images; None = raw.
        scan: Write ``scan`` (``sensor_msgs/LaserScan`` of the kept pixels) with this band,
            ranges and pitch (the node's ``scan_*`` parameters); None = no scan.
        scan_frame_id: Frame of ``scan``; ``''`` = the camera's body frame
            (:func:`cva_confidence_ros.scan.scan_frame_id`).
        overwrite: Replace an existing output bag (it is replaced only once the new one holds
            a frame) and the files of an earlier report in the report folder.
        rate_scale: Live mode: play at this multiple of the recorded speed.
        start_node: Live mode: start ``cva-node`` (else connect to a running one).
        startup_timeout_s: Live mode: wait this long for the node's topics to connect.
        drain_timeout_s: Live mode: after the last input, wait this long without any output
            before giving up on the frames not answered yet.
        start_s: Replay from this many seconds after the bag's first message (bag time, as
            ``ros2 bag play --start-offset``).
        duration_s: Replay this many seconds of the bag from there; None = to its end.

    Raises:
        ConfigError: An invalid value or path; one of given fields (or topics) carries their
            names in ``fields``, for a caller that set them under other names (the command
            line's options, :mod:`msg_tools.bag_replay`).
    """

    bag: Path
    out: Path
    report: Path
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    topics: TopicNames = field(default_factory=TopicNames)
    gt_required: bool = False
    mode: str = 'offline'
    storage: str = 'mcap'
    approximate_sync: bool = False
    sync_tolerance_s: float = 0.0
    queue_size: int = 10
    max_pixels: int | None = None
    seed: int = 0
    max_plots: int = 10
    publish_points: bool = True
    points_organized: bool = True
    points_confidence: bool = False
    publish_depth: bool = True
    depth_encoding: str = '32FC1'
    publish_overlay: bool = False
    compressed: CompressionConfig | None = None
    scan: ScanConfig | None = None
    scan_frame_id: str = ''
    overwrite: bool = False
    rate_scale: float = 1.0
    start_node: bool = True
    startup_timeout_s: float = 60.0
    drain_timeout_s: float = 30.0
    start_s: float = 0.0
    duration_s: float | None = None

    def __post_init__(self) -> None:
        if self.mode not in ('offline', 'live'):
            raise ConfigError(f"mode must be 'offline' or 'live'; got {self.mode!r}", 'mode')
        if self.storage not in STORAGES:
            raise ConfigError(
                f'storage must be one of {STORAGES}; got {self.storage!r}', 'storage'
            )
        if self.queue_size < 1:
            raise ConfigError(f'queue_size must be >= 1; got {self.queue_size}', 'queue_size')
        from cva_confidence_ros.ros.convert import DEPTH_ENCODINGS

        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise ConfigError(
                f'depth encoding must be one of {DEPTH_ENCODINGS}; got {self.depth_encoding!r}',
                'depth_encoding',
            )
        if not 0 <= self.sync_tolerance_s <= _MAX_SPAN_S:
            raise ConfigError(
                f'sync tolerance must be a finite number of seconds >= 0 (at most '
                f'{_MAX_SPAN_S:.3g}, the span of int64 ns stamps); got {self.sync_tolerance_s}',
                'sync_tolerance_s',
            )
        if self.max_pixels is not None and self.max_pixels < 1:
            raise ConfigError(f'max_pixels must be >= 1; got {self.max_pixels}', 'max_pixels')
        if self.max_plots < 0:
            raise ConfigError(f'max_plots must be >= 0; got {self.max_plots}', 'max_plots')
        if self.seed < 0:
            # numpy's generators take no negative seed; the run would fail at its first frame.
            raise ConfigError(f'seed must be an integer >= 0; got {self.seed}', 'seed')
        if not (math.isfinite(self.rate_scale) and self.rate_scale > 0):
            raise ConfigError(
                f'rate_scale must be a finite number > 0; got {self.rate_scale}', 'rate_scale'
            )
        timeouts = {'startup_timeout_s': self.startup_timeout_s,
                    'drain_timeout_s': self.drain_timeout_s}
        bad = [name for name, t in timeouts.items() if not (math.isfinite(t) and t > 0)]
        if bad:
            raise ConfigError(
                f'timeouts must be a finite number of seconds > 0; got startup '
                f'{self.startup_timeout_s}, drain {self.drain_timeout_s}', *bad,
            )
        if not (math.isfinite(self.start_s) and 0 <= self.start_s <= _MAX_SPAN_S):
            raise ConfigError(
                f'start must be a finite number of seconds >= 0; got {self.start_s}', 'start_s'
            )
        if self.duration_s is not None and not (
            math.isfinite(self.duration_s) and 0 < self.duration_s <= _MAX_SPAN_S
        ):
            raise ConfigError(
                f'duration must be a finite number of seconds > 0; got {self.duration_s}',
                'duration_s',
            )
        self._check_paths()

    def bag_window(self, bag: InputBag) -> tuple[int | None, int | None]:
        """The bag times (ns) to replay, ``[start, stop)``, from ``start_s`` and
        ``duration_s``; (None, None) = the whole bag.

        Raises:
            ConfigError: ``start_s`` at or past the bag's end (naming the bag's length).
        """
        if self.start_s == 0 and self.duration_s is None:
            return None, None
        first, end = bag.time_range
        start = first + int(round(self.start_s * 1e9))
        if start >= end:
            raise ConfigError(
                f'start {self.start_s:g} s lies at or past the end of bag {self.bag}, which '
                f'spans {(end - first) / 1e9:.3f} s of bag time', 'start_s',
            )
        stop = None if self.duration_s is None else start + int(round(self.duration_s * 1e9))
        return start, stop

    def _check_paths(self) -> None:
        """Refuse outputs that would write over the input or over each other, an output bag
        or report folder that cannot be made because a file is in the way, and, before any
        work, earlier outputs without ``overwrite``.

        ``--overwrite`` deletes the old output bag, so an output that is the input, holds
        it or lies in it would destroy the input; a report folder in the output bag would
        make the bag's folder exist before the bag is created. An existing output bag needs
        ``overwrite`` and must be a bag; a report folder that holds something needs
        ``overwrite`` and must hold an earlier report (``scoring.check_report_folder``).
        """
        bag, out, report = (Path(p).resolve() for p in (self.bag, self.out, self.report))
        if out == bag or bag in out.parents:
            raise ConfigError(
                f'the output bag must lie outside the input bag; got --out {self.out} for the '
                f'input {self.bag}'
            )
        if out in bag.parents:
            raise ConfigError(
                f'the output bag must not contain the input bag (--overwrite would delete '
                f'it); got --out {self.out} for the input {self.bag}'
            )
        if report == out or out in report.parents:
            raise ConfigError(
                f'the report folder must lie outside the output bag; got --report '
                f'{self.report} and --out {self.out}'
            )
        if report == bag or bag in report.parents:
            raise ConfigError(
                f'the report folder must lie outside the input bag; got --report '
                f'{self.report} for the input {self.bag}'
            )
        existing = next(p for p in (report, *report.parents) if p.exists())
        if existing == report and not report.is_dir():
            raise ConfigError(f'the report folder {self.report} is a file; expected a folder')
        if not existing.is_dir():
            raise ConfigError(
                f'cannot create the report folder {self.report}: {existing} is a file'
            )
        # Checked here, not when the bag is opened: by then --overwrite has cleared the report.
        holder = next(p for p in out.parents if p.exists())
        if not holder.is_dir():
            raise ConfigError(
                f'cannot create output bag {self.out}: {holder} is a file, not a folder'
            )
        if Path(self.out).exists() or Path(self.out).is_symlink():
            if not self.overwrite:
                raise ConfigError(
                    f'output bag {self.out} exists already; use --overwrite to replace it, or '
                    f'pick another'
                )
            check_replaceable(self.out)
        # The bags may lie inside the report folder: they are not part of a report.
        ignore = {bag, out, *bag.parents, *out.parents, staging_folder(out).resolve()}
        check_report_folder(self.report, self.overwrite, ignore)

    def config_record(self) -> dict[str, Any]:
        """The ``config`` block of ``report.json``."""
        record: dict[str, Any] = {
            'bag': str(self.bag),
            'out': str(self.out),
            'mode': self.mode,
            **asdict(self.pipeline),
            'gt_topic': self.topics.resolve('ground_truth'),
            'topics': {**self.topics.inputs(), **self.topics.outputs()},
            'approximate_sync': self.approximate_sync,
            'sync_tolerance_s': self.sync_tolerance_s,
            'queue_size': self.queue_size,
            'max_pixels': self.max_pixels,
            'seed': self.seed,
            'compressed': None if self.compressed is None else asdict(self.compressed),
        }
        if self.mode == 'live':
            record.update(rate_scale=self.rate_scale, start_node=self.start_node)
        if self.start_s or self.duration_s is not None:
            record.update(start_s=self.start_s, duration_s=self.duration_s)
        return record


@dataclass(frozen=True)
class TopicPlan:
    """What the input bag offers for the replay.

    Attributes:
        inputs: Synchroniser key → absolute topic.
        input_types: Absolute topic → message type, for the four inputs.
        ground_truth: Ground-truth topic, or None when the bag has none.
        ground_truth_type: Its message type ('' without one).
        pairs_expected: Number of left images in the bag (for the progress line).
        input_counts: Absolute input topic → number of messages (as the bag's metadata
            states).
        window: Bag times (ns) replayed, ``[start, stop)`` (:meth:`ReplayOptions.bag_window`);
            the counts are those within it.
    """

    inputs: dict[str, str]
    input_types: dict[str, str]
    ground_truth: str | None
    ground_truth_type: str
    pairs_expected: int
    input_counts: dict[str, int] = field(default_factory=dict)
    window: tuple[int | None, int | None] = (None, None)

    @property
    def key_of(self) -> dict[str, str]:
        """Absolute input topic → synchroniser key."""
        return {topic: key for key, topic in self.inputs.items()}

    @property
    def topics(self) -> list[str]:
        """Every topic the replay reads."""
        return [*self.inputs.values(), *([self.ground_truth] if self.ground_truth else [])]

    @property
    def image_transport(self) -> str:
        """``raw`` or ``compressed``: how both images are stored (the node's parameter).

        Raises:
            ConfigError: One image raw, the other compressed (one node takes one transport).
        """
        kinds = {self.input_types[self.inputs[key]] for key in ('left', 'right')}
        if len(kinds) > 1:
            raise ConfigError(
                f'left and right images differ in type ({", ".join(sorted(kinds))}); a node '
                'subscribes to both with one image_transport'
            )
        return 'compressed' if kinds == {COMPRESSED_IMAGE} else 'raw'


def plan_topics(bag: InputBag, options: ReplayOptions, log: Logger = log_stderr) -> TopicPlan:
    """Check that the bag has the input topics (and the ground truth if asked for).

    The ground-truth topic is used when the bag has it with a ground-truth type; one asked
    for explicitly (``options.gt_required``) must be there with such a type, while the
    default one of another type is ignored with a log line.

    Raises:
        BagError: An empty bag (no topic at all), a missing input topic, one of the wrong
            type, or a ground-truth topic that was asked for explicitly and is missing or of
            another type.
        ConfigError: A ``start_s`` past the bag's end.
    """
    if not bag.topics:
        raise BagError(f'bag {bag.path} is empty (0 messages)')
    inputs = options.topics.inputs()
    types = {}
    for key, topic in inputs.items():
        try:
            types[topic] = bag.require(topic, _INPUT_TYPES[key], key.replace('_', ' '))
        except BagError as err:
            if topic in bag.topics:
                raise
            raise BagError(f'{err}{_camera_hint(bag.topics, options.topics)}') from None
    gt_topic = options.topics.resolve('ground_truth')
    gt_type = ''
    ground_truth: str | None = gt_topic
    found = bag.topics.get(gt_topic)
    if options.gt_required:
        gt_type = bag.require(gt_topic, GT_TYPES, 'ground-truth')
    elif found is None:
        log(f'no ground-truth topic {gt_topic} in the bag: frames are processed, not scored')
        ground_truth = None
    elif found not in GT_TYPES:
        # The default name, not asked for: a topic of that name that is no ground truth is
        # left alone rather than refusing the whole run.
        log(
            f'topic {gt_topic} of the bag has type {found}, not a ground truth '
            f'({" or ".join(GT_TYPES)}): it is not used, frames are processed, not scored '
            f'(name the ground-truth topic with --gt-topic)'
        )
        ground_truth = None
    else:
        gt_type = found
    counts = bag.message_counts
    window = options.bag_window(bag)
    if window != (None, None):
        # Counted in the part replayed (the metadata counts the whole bag).
        counts = Counter(topic for topic, *_ in bag.messages(list(inputs.values()), *window))
    return TopicPlan(
        inputs=inputs,
        input_types=types,
        ground_truth=ground_truth,
        ground_truth_type=gt_type,
        pairs_expected=counts.get(inputs['left'], 0),
        input_counts={topic: counts.get(topic, 0) for topic in inputs.values()},
        window=window,
    )


def _camera_hint(topics: dict[str, str], names: TopicNames) -> str:
    """The stereo cameras a bag holds under other namespaces than the options name, as the
    ``--topic-prefix`` of each (a robot's bag lists a hundred topics or more)."""
    if names.left.startswith('/') or names.right.startswith('/'):
        return ''
    left, right = names.left.strip('/'), names.right.strip('/')
    found = []
    for topic, kind in sorted(topics.items()):
        for transport in ('', '/compressed'):
            if not topic.endswith(f'/{left}{transport}') or kind not in _INPUT_TYPES['left']:
                continue
            prefix = topic[: -len(f'/{left}{transport}')]
            if f'{prefix}/{right}{transport}' not in topics:
                continue
            option = f'--topic-prefix {prefix or "/"}'
            if transport:
                option += (f' --left-topic {left}{transport} --right-topic '
                           f'{right}{transport}')
            found.append(option)
    if not found:
        return ''
    return f'; stereo cameras in the bag: {" | ".join(found)}'


def stereo_inputs(
    items: dict[str, Any],
) -> tuple[np.ndarray, np.ndarray, StereoGeometry]:
    """Decode one matched set of messages into the pipeline's inputs, as the node does.

    The node's own decoder is used (``ros.convert.stereo_pair_from_messages``; it reads the
    message fields only, so ``rosbags`` messages work), so a frame the node would drop is
    skipped here for the same reason.

    Args:
        items: Synchroniser key → message, keys :data:`INPUT_KEYS`.

    Returns:
        ``(left, right, geometry)``: uint8 images (RGB or gray) and the stereo geometry at
        their resolution.

    Raises:
        InputError: Unknown encoding, camera infos that do not fit, or size mismatches.
    """
    from cva_confidence_ros.ros.convert import stereo_pair_from_messages

    return stereo_pair_from_messages(
        items['left'], items['right'], items['left_info'], items['right_info']
    )


def output_left_image(
    items: dict[str, Any], shape: tuple[int, ...], downsample: int
) -> np.ndarray | None:
    """The left image of a matched set as the node processes it (decoded as
    :func:`stereo_inputs`, shrunk by ``downsample`` as the pipeline does), or None when it
    does not decode or does not come out at ``shape``, the (h, w) of the node's outputs."""
    from cva_confidence_ros.datasets.resize import resize_image

    try:
        left = resize_image(stereo_inputs(items)[0], downsample)
    except CVAError:
        return None
    return left if left.shape[:2] == tuple(shape[:2]) else None


@dataclass
class NodeOutputs:
    """What the node publishes for one frame: serialised messages and the arrays behind them.

    Attributes:
        messages: ``(output name, message type, CDR bytes)`` for ``disparity``,
            ``confidence``, ``disparity_filtered`` and (optionally) ``points``, ``depth`` or
            ``depth_compressed``, ``overlay`` or ``overlay_compressed``, ``scan`` and
            ``camera_info``.
        confidence: (h, w) float32 published confidence in [0, 1].
        kept: (h, w) bool, pixels kept by the threshold and the speckle filter (finite in
            ``disparity_filtered``).
        geometry: Stereo geometry at the processed resolution.
    """

    messages: list[tuple[str, str, bytes]]
    confidence: np.ndarray
    kept: np.ndarray
    geometry: StereoGeometry


def node_outputs(
    result: PipelineResult,
    geometry: StereoGeometry,
    input_shape: tuple[int, int],
    header: Any,
    config: PipelineConfig,
    *,
    publish_points: bool = True,
    points_organized: bool = True,
    points_confidence: bool = False,
    publish_depth: bool = True,
    depth_encoding: str = '32FC1',
    publish_overlay: bool = False,
    compressed: CompressionConfig | None = None,
    scan: ScanConfig | None = None,
    scan_frame_id: str = '',
    left_info: Any = None,
) -> NodeOutputs:
    """The messages the node publishes for one processed pair, built by the node's own code.

    Mirrors ``ConfidenceNode._publish``: geometry scaled to the processed size, confidence
    in [0, 1] (the pipeline's fixed per-method map), kept = ``result.valid`` (finite disparity,
    confidence ≥ threshold, not in a speckle), messages from ``ros.convert`` serialised by
    rclpy, so the bytes are those the node would send.

    Args:
        result: The pipeline's output at the processed resolution.
        geometry: Stereo geometry of the input camera infos (input resolution).
        input_shape: Input ``(height, width)``: what a camera info with binning or a region
            of interest is folded to (the scale is ``result.scale``, exactly 1/downsample, as
            the node uses).
        header: Header of the left image (``rosbags`` or rclpy; stamp and frame id are used).
        config: The pipeline settings.
        publish_points: Include ``points2``.
        points_organized: Organised cloud (H×W, NaN points) or only the kept points.
        points_confidence: Every triangulated point with a ``confidence`` field instead of
            only the kept ones.
        publish_depth: Include ``depth``, the depth of the kept pixels.
        depth_encoding: Its encoding, ``32FC1`` or ``16UC1``.
        publish_overlay: Include ``confidence_overlay`` (``plots.confidence_overlay``, rgb8).
        compressed: Given, ``depth`` and ``confidence_overlay`` come as the node's
            compressed transports instead (``depth_compressed``, ``overlay_compressed``:
            ``ros.transport.depth_image_to_compressed_depth`` of the depth image and
            ``rgb_to_compressed`` of the overlay, JPEG, with these settings).
        scan: Include ``scan`` (``scan.disparity_to_scan`` with this config); None = not.
        scan_frame_id: Its frame; ``''`` = ``scan.scan_frame_id`` of the left image's frame.
        left_info: The left camera info of the input (``rosbags`` or rclpy); given, include
            ``camera_info`` scaled to the output resolution, as the node publishes it.

    Returns:
        The :class:`NodeOutputs`.
    """
    from builtin_interfaces.msg import Time
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header

    from cva_confidence_ros.plots import confidence_overlay
    from cva_confidence_ros.pointcloud import disparity_to_depth, stereo_cloud
    from cva_confidence_ros.ros.convert import (
        array_to_image,
        cloud_to_message,
        depth_to_image,
        disparity_to_message,
        image_camera_info,
        rgb_to_image,
        scale_camera_info,
        scan_to_message,
    )
    from cva_confidence_ros.ros.transport import (
        depth_image_to_compressed_depth,
        rgb_to_compressed,
    )
    from cva_confidence_ros.scan import disparity_to_scan
    from cva_confidence_ros.scan import scan_frame_id as body_frame

    ros_header = Header(
        stamp=Time(sec=int(header.stamp.sec), nanosec=int(header.stamp.nanosec)),
        frame_id=str(header.frame_id),
    )
    disparity = result.disparity
    if result.scale != 1.0:
        # As the node: the pipeline crops the bottom/right rest and shrinks by exactly
        # 1/downsample (out_w / in_w would be off for an odd size).
        geometry = geometry.scaled(result.scale)
    confidence = np.clip(np.nan_to_num(result.confidence, nan=0.0), 0.0, 1.0)
    kept = result.valid
    filtered = result.filtered_disparity
    messages = [
        ('disparity', DISPARITY_IMAGE,
         disparity_to_message(
             disparity, ros_header, geometry, config.max_disparity, config.disparity_step
         )),
        ('confidence', IMAGE, array_to_image(confidence, ros_header)),
        ('disparity_filtered', DISPARITY_IMAGE,
         disparity_to_message(
             filtered, ros_header, geometry, config.max_disparity, config.disparity_step
         )),
    ]
    if publish_points:
        cloud = stereo_cloud(
            disparity,
            confidence,
            result.left,
            geometry,
            kept,
            organized=points_organized,
            with_confidence=points_confidence,
        )
        messages.append(('points', POINT_CLOUD2, cloud_to_message(cloud, ros_header)))
    if publish_depth:
        depth = disparity_to_depth(disparity, geometry, kept)
        depth_msg = depth_to_image(depth, ros_header, depth_encoding)
        if compressed is None:
            messages.append(('depth', IMAGE, depth_msg))
        else:
            messages.append(
                ('depth_compressed', COMPRESSED_IMAGE,
                 depth_image_to_compressed_depth(
                     depth_msg,
                     compressed.compressed_depth_max,
                     compressed.compressed_depth_quantization,
                     compressed.compressed_depth_png_level,
                 ))
            )
    if publish_overlay:
        overlay = confidence_overlay(result.left, confidence, kept)
        if compressed is None:
            messages.append(('overlay', IMAGE, rgb_to_image(overlay, ros_header)))
        else:
            messages.append(
                ('overlay_compressed', COMPRESSED_IMAGE,
                 rgb_to_compressed(
                     overlay, ros_header, jpeg_quality=compressed.overlay_jpeg_quality
                 ))
            )
    if scan is not None:
        laser = disparity_to_scan(disparity, geometry, kept, confidence, scan)
        frame = body_frame(ros_header.frame_id, scan_frame_id)
        messages.append(('scan', LASER_SCAN, scan_to_message(laser, ros_header, frame)))
    if left_info is not None:
        messages.append(
            ('camera_info', CAMERA_INFO,
             scale_camera_info(image_camera_info(left_info, input_shape[1], input_shape[0]),
                               config.downsample, ros_header))
        )
    store = jazzy_typestore()
    # rclpy leaves CDR alignment padding uninitialised; a pass through rosbags zeroes it, so
    # that the same input always gives the same output bag, byte for byte.
    return NodeOutputs(
        messages=[
            (name, kind, bytes(store.serialize_cdr(
                store.deserialize_cdr(serialize_message(msg), kind), kind)))
            for name, kind, msg in messages
        ],
        confidence=confidence,
        kept=kept,
        geometry=geometry,
    )


@dataclass
class FrameResult:
    """A processed frame waiting for (or scored against) its ground truth.

    Attributes:
        frame: Index of the pair in the bag. stamp_ns: Its stamp.
        disparity: (h, w) float32 raw disparity (x_left − x_right), NaN invalid.
        confidence: (h, w) float32 published confidence.
        kept: (h, w) bool, pixels the node keeps.
        offset: Δ = cx_right − cx_left at the input resolution, to read a ground-truth
            ``DisparityImage`` at that resolution (which holds d + Δ; one at the output
            resolution holds the Δ of ``geometry``).
        processing_ms: Pipeline time (offline). latency_ms: Live round-trip time.
        image: Returns the left image at the output resolution (uint8) for the report's
            overlays, or None where it cannot be had; called only for frames drawn.
        region: (h, w) bool, the pixels the node judges (``PipelineResult.region``: the
            region of interest and the ignore mask); None = all.
        geometry: Stereo geometry at the output resolution (to score ``--scan``).
        input_shape: (h, w) of the input images: ground truth of another size than this (or
            the output's) is refused. None = unknown: ground truth whose size shrinks to the
            output's by the downsample factor is taken as of the input size.
    """

    frame: int
    stamp_ns: int
    disparity: np.ndarray
    confidence: np.ndarray
    kept: np.ndarray
    offset: float = 0.0
    processing_ms: float | None = None
    latency_ms: float | None = None
    image: Callable[[], np.ndarray | None] | None = None
    region: np.ndarray | None = None
    geometry: StereoGeometry | None = None
    input_shape: tuple[int, int] | None = None


@dataclass
class ReplayOutcome:
    """How a run ended: the report, where the outputs are, and the exit code."""

    report: ReplayReport
    paths: dict[str, Path]
    exit_code: int
    message: str


class ReplaySession:
    """Output bag, ground-truth pairing, scoring and report, shared by both modes.

    Use as a context manager: leaving it (normally, on a bag fault, or on Ctrl-C) finalises
    the output bag and writes the report with the frames done so far; the two expected ways
    to stop early (``KeyboardInterrupt``, ``BagError``) are recorded in the report and not
    raised further, see :meth:`outcome`; another error of the package (a report folder that
    is full) is recorded in the report too, and raised further.

    Ground truth and results meet by stamp: whichever comes first waits. The ground-truth
    topic comes in stamp order but for messages a little out of order (a ground-truth node
    whose latency varies: less than :data:`TRUTH_JUMP_NS`), so a result stops waiting once
    ground truth of a stamp that much later has been read (its own can no longer come), or
    when the truth stamps jump back past it, or when :data:`GT_WAIT_FRAMES` results wait
    (ground truth that lags its images by more is not waited for); it is then reported
    unscored, with the reason. A frame that cannot be scored (no usable ground truth) is
    logged with the reason (the first few times per reason).

    Stamps that go back on either stream (a looped bag, a simulator reset; on the frames,
    the synchroniser lets a frame go back only where the stamps jumped; on the ground truth,
    :data:`TRUTH_JUMP_NS` or more, or two messages in a row before the last, or one while the
    frames jump: one message a little out of order is taken in the epoch it belongs to) start
    a new ordering epoch of that stream, and the n-th jump of the frames and of the ground
    truth are taken as the same one: only ground truth of a frame's own epoch tells that its
    ground truth can no longer come. Frames from before a jump still wait for theirs (it may
    lag); one that a frame of the same stamp after the jump finds waiting is reported
    unscored. Ground truth does not score a frame of an earlier epoch, nor does ground truth
    left from an earlier epoch (a skipped frame's) score a frame after a jump.

    The synchroniser records the input messages it lets go without a pair
    (:meth:`report_drops`): each is logged (the first few) and recorded in the report with its
    topic, stamp and why (no partner, duplicate stamp, late).

    Args:
        options: The run's options.
        plan: The topic plan of the input bag.
        log: Receives one-line messages.
        truth_window: Most ground-truth messages held while waiting for their frame (the
            oldest goes first); 0 = :data:`GT_WAIT_FRAMES`; None = unbounded, the caller
            evicts with :meth:`drop_ground_truth_before`.
        interrupts: The run's Ctrl-C handling, when it began before the session; the session
            enters it again and calls :meth:`GracefulInterrupt.closing` when it ends.
    """

    def __init__(
        self,
        options: ReplayOptions,
        plan: TopicPlan,
        log: Logger = log_stderr,
        truth_window: int | None = 0,
        interrupts: GracefulInterrupt | None = None,
    ) -> None:
        self.options = options
        self.plan = plan
        self.log = log
        self.report = ReplayReport(config=options.config_record())
        self.report.counts.update(
            total=plan.pairs_expected, pairs=0, processed=0, skipped=0, unpaired=0, dropped=0,
            unreadable=0, gt_unmatched=0,
        )
        self.interrupts = interrupts or GracefulInterrupt()
        self._report_lock = ReportFolderLock(options.report)
        self.out: OutputBag | None = None
        self.writer: ReportWriter | None = None
        self.paths: dict[str, Path] = {}
        self.truth_window = GT_WAIT_FRAMES if truth_window == 0 else truth_window
        # Stamp → (ordering epoch, frame or ground-truth message), see the class.
        self._pending: OrderedDict[int, tuple[int, FrameResult]] = OrderedDict()
        self._truth: OrderedDict[int, tuple[int, Any]] = OrderedDict()
        # Epochs and last stamps of the frames' and the ground truth's streams.
        self._frame_epoch = self._truth_epoch = 0
        self._last_frame: int | None = None
        self._last_truth: int | None = None
        # A ground-truth message a little before the last: out of order or the first after a
        # short jump back, told apart by what comes next (see add_ground_truth).
        self._truth_held: tuple[int, Any] | None = None
        # Stamps (→ epoch) of frames that stopped waiting after GT_WAIT_FRAMES, and of ground
        # truth that waited longer than truth_window for its frame: to tell why a frame went
        # unscored. A dropped ground truth's epoch is kept while it counts as matching no
        # frame (None once not: its frame came after all, or one of its stamp was done).
        self._given_up: OrderedDict[int, int | None] = OrderedDict()
        self._truth_dropped: OrderedDict[int, int | None] = OrderedDict()
        # (Stamp, epoch) of the processed frames, to tell a second ground-truth message of a
        # frame's stamp from one that matched no frame.
        self._processed: OrderedDict[tuple[int, int], None] = OrderedDict()
        # Stamps of the skipped frames: their ground truth matched no processed frame, but it
        # is stamped right (the closing line must not blame its stamps).
        self._skipped: OrderedDict[int, None] = OrderedDict()
        # Stamps (→ epoch) of left images the synchroniser let go as late (out of order).
        self._late_frames: OrderedDict[int, int] = OrderedDict()
        self._late_truth_logged = False
        self._skip_logs = 0
        # Ground-truth messages that could not be read (their stamps are unknown).
        self._unreadable_truth = 0
        self._unpaired_logs = 0
        self._unscored_logs: Counter[str] = Counter()

    def __enter__(self) -> ReplaySession:
        # The output bag's folder is tried before --overwrite clears the old report, so that a
        # run that cannot write its bag leaves the old outputs alone; then the report folder,
        # before the bag is opened: a --report that cannot be created must not cost the old
        # output bag. A live run did both before it started the node (whose log is there).
        if self.options.mode != 'live':
            check_output_bag_folder(self.options.out)
        # Held to the end of the run, before the old report is cleared: a second run into
        # this report folder now is refused instead of mixing its files with ours.
        self._report_lock.__enter__()
        try:
            if self.options.overwrite and self.options.mode != 'live':
                clear_report(self.options.report)
            pipeline = self.options.pipeline
            self.writer = ReportWriter(
                self.options.report, self.options.max_plots, self.plan.pairs_expected,
                run=f'{pipeline.matcher} + {pipeline.confidence_method}, '
                f'D = {pipeline.max_disparity}',
            )
        except BaseException:
            self._report_lock.__exit__()
            raise
        self.interrupts.__enter__()
        try:
            # With --overwrite the old bag is replaced only once the new one holds a frame.
            # A run that writes nothing leaves no new bag (a retry needs no --overwrite for it).
            self.out = OutputBag(
                self.options.out, self.options.storage, overwrite=self.options.overwrite,
                keep_empty=False,
            )
            self.out.open()
        except BaseException:
            self.interrupts.__exit__()
            self._report_lock.__exit__()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> bool:
        self.interrupts.closing()
        # A second Ctrl-C is raised at once, possibly inside a numba kernel's hand-over of its
        # result, where it comes out as a SystemError (see from_interrupt).
        interrupted = exc is not None and from_interrupt(exc)
        try:
            if interrupted:
                self.report.interrupted = True
            elif isinstance(exc, CVAError):
                # A bag fault ends the run here; another fault (a report folder that is full)
                # is raised further, but the report says what stopped it all the same.
                self.report.error = str(exc)
            self.finish()
        finally:
            self.interrupts.__exit__()
            self._report_lock.__exit__()
        return interrupted or isinstance(exc, BagError)

    @property
    def counts(self) -> dict[str, int]:
        """Frame counters of the report (``pairs``, ``processed``, ``skipped``, ...)."""
        return self.report.counts

    def skip(self, what: str, reason: object, stamp_ns: int | None = None) -> None:
        """Count a bad frame (a stereo pair that was not processed, of stamp ``stamp_ns``
        where known) and log it (the first few times)."""
        self.counts['skipped'] += 1
        if stamp_ns is not None:
            _remember(self._skipped, stamp_ns)
        self._log_skip(what, reason)

    def unreadable(self, topic: str, timestamp_ns: int, reason: object) -> None:
        """Count an input message that cannot be deserialised, and log it (the first few
        times). It is no stereo pair: ``skipped`` counts pairs (``pairs`` = ``processed`` +
        ``skipped`` offline); its partners are reported unpaired."""
        self.counts['unreadable'] = self.counts.get('unreadable', 0) + 1
        if topic == self.plan.ground_truth:
            self._unreadable_truth += 1
        self._log_skip(f'a message on {topic} at {timestamp_ns} ns', reason)

    def _log_skip(self, what: str, reason: object) -> None:
        self._skip_logs += 1
        if self._skip_logs <= _MAX_SKIP_LOGS:
            self.log(f'skipped {what}: {reason}')
        elif self._skip_logs == _MAX_SKIP_LOGS + 1:
            self.log('more frames skipped; only counting them from now on')

    def report_drops(self, sync: Any, stopped: bool = False) -> None:
        """Log and record the input messages the synchroniser let go without a pair
        (``record_drops=True``; call after each message and after ``sync.drain()``).

        ``stopped``: the run stopped before the end of the bag (Ctrl-C, a bag fault) and
        ``sync.drain()`` let go the messages still waiting; those say so (their partners may
        lie further on in the bag).
        """
        for drop in sync.take_drops():
            if drop.kind == 'late' and drop.key == 'left':
                # A frame out of order: its ground truth may come out of order too.
                _remember(self._late_frames, drop.stamp_ns, self._frame_epoch)
            why = self._why(drop)
            if stopped and drop.kind == 'unmatched':
                why = 'still waiting for its partners when the run stopped'
            self._unpaired(drop.key, drop.stamp_ns, why)

    def _why(self, drop: Any) -> str:
        """A drop's reason in words, naming the inputs that lacked its stamp."""
        topic = self.plan.inputs[drop.key]
        if drop.kind == 'duplicate':
            return (f'duplicate stamp: a later message on {topic} has the same stamp and '
                    'took its place')
        if drop.kind == 'repeat':
            return (f'duplicate stamp: an earlier message on {topic} has the same stamp and '
                    'was paired')
        if drop.kind == 'late':
            return f'late: older than the last pair on {topic}'
        if drop.kind == 'overflow':
            return (f'the queue of {topic} was full ({self.options.queue_size} messages): the '
                    'oldest went')
        if drop.kind == 'jump':
            return 'the stamps jumped back while it waited; pairing started over'
        if self.options.approximate_sync:
            return (
                f'no partner within the sync tolerance ({self.options.sync_tolerance_s:g} s) '
                f'on every input'
            )
        missing = []
        for other, stamps in drop.others.items():
            if drop.stamp_ns in stamps:
                continue
            text = self.plan.inputs[other]
            if stamps:
                nearest = min(stamps, key=lambda s: abs(s - drop.stamp_ns))
                text += f' (nearest {_offset(nearest - drop.stamp_ns)})'
            missing.append(text)
        if not missing:
            return 'no partner (its partners were paired or dropped before it came)'
        return 'no message with this stamp on ' + ', '.join(missing)

    def _unpaired(self, key: str, stamp_ns: int, why: str) -> None:
        topic = self.plan.inputs[key]
        self.report.add_unpaired(topic, stamp_ns, why)
        self._unpaired_logs += 1
        if self._unpaired_logs <= _MAX_UNPAIRED_LOGS:
            self.log(f'unpaired {_KEY_NAMES.get(key, key)} on {topic}, stamp {stamp_ns} ns: '
                     f'{why}')
        elif self._unpaired_logs == _MAX_UNPAIRED_LOGS + 1:
            self.log('more unpaired messages; only counting them from now on (report.json '
                     'lists the first ones)')

    def write(self, messages: list[tuple[str, str, Any]], timestamp_ns: int) -> None:
        """Write ``(topic, type, message or CDR bytes)`` triples at one bag time; a signal
        waits until all are written, so a frame is in the bag whole or not at all."""
        if self.out is None:
            raise BagError('the output bag is not open')
        with self.interrupts.critical():
            for topic, msgtype, message in messages:
                self.out.write(topic, msgtype, message, timestamp_ns)

    def add_ground_truth(self, stamp_ns: int, msg: Any) -> None:
        """Offer a ground-truth message; scores the frame that waits for it, if any, and
        gives up on the frames of older stamps of its epoch that still wait (theirs can no
        longer come). A stamp :data:`TRUTH_JUMP_NS` or more before the last one starts a new
        epoch; one less before it waits for the next message (or frame): when that goes back
        too, the stamps jumped; else it was out of order if a frame of its stamp came before
        it, or the frames have not reached its stamp yet (see the class)."""
        if self._truth_held is not None:
            assert self._last_truth is not None
            self._release_truth(jumped=True if stamp_ns < self._last_truth else None)
        last = self._last_truth
        if last is not None and 0 < last - stamp_ns < TRUTH_JUMP_NS:
            self._truth_held = (stamp_ns, msg)
            return
        self._take_truth(stamp_ns, msg)

    def _release_truth(self, jumped: bool | None = None) -> None:
        """Take the ground-truth message held aside: as the first after a jump back, or as
        one out of order (its epoch, the last stamp unchanged); None: out of order when a
        frame of its stamp was processed (or waits, or came late) in the ground truth's epoch,
        or the frames of that epoch have not come as far as its stamp, else a jump (a
        reset)."""
        held, self._truth_held = self._truth_held, None
        if held is None:
            return
        if jumped is None:
            stamp, epoch = held[0], self._truth_epoch
            seen = (
                (stamp, epoch) in self._processed
                or self._late_frames.get(stamp) == epoch
                or (stamp in self._pending and self._pending[stamp][0] == epoch)
            )
            ahead = epoch == self._frame_epoch and (
                self._last_frame is None or stamp > self._last_frame
            )
            jumped = not (seen or ahead)
        self._take_truth(*held, in_order=jumped)

    def _take_truth(self, stamp_ns: int, msg: Any, in_order: bool = True) -> None:
        """:meth:`add_ground_truth` proper; ``in_order`` False: a message out of order, taken
        in the current epoch without moving the last stamp."""
        if in_order:
            if self._last_truth is not None and stamp_ns < self._last_truth:
                # The frames of the epoch that ends whose ground truth was passed get none.
                self._give_up_before(self._last_truth, self._truth_epoch, window=0)
                self._truth_epoch += 1
            self._last_truth = stamp_ns
        epoch = self._truth_epoch
        self._give_up_before(stamp_ns, epoch)
        waiting = self._pending.get(stamp_ns)
        if waiting is not None and waiting[0] >= epoch:
            # A frame from before a jump back is left waiting: its own came before the jump.
            del self._pending[stamp_ns]
            self._score(waiting[1], msg)
            return
        if stamp_ns in self._given_up and self._given_up[stamp_ns] == epoch:
            if not self._late_truth_logged:
                self._late_truth_logged = True
                self.log(
                    f'the ground truth of stamp {stamp_ns} ns came {GT_WAIT_FRAMES} or more '
                    f'frames after its images; a frame waits for it only until '
                    f'{GT_WAIT_FRAMES} later frames have come, so frames like it stay unscored'
                )
            return
        earlier = self._truth.pop(stamp_ns, None)  # the newer goes last
        if earlier is not None and earlier[0] != epoch:
            # One of an earlier pass that no frame took (a second one of this pass stands for
            # itself).
            self._truth_unused(stamp_ns, earlier[0])
        self._truth[stamp_ns] = (epoch, msg)
        while self.truth_window is not None and len(self._truth) > self.truth_window:
            dropped, (dropped_epoch, _) = self._truth.popitem(last=False)
            # Counted now (its frame is rarely still to come); taken back if it comes.
            counted = self._truth_unused(dropped, dropped_epoch)
            _remember(self._truth_dropped, dropped, dropped_epoch if counted else None)

    def drop_ground_truth_before(self, stamp_ns: int) -> None:
        """Forget ground truth older than ``stamp_ns`` (frames that will never come) of the
        frames' epoch; that of another epoch (before or after a jump) is kept."""
        for stamp in [s for s, (e, _) in self._truth.items()
                      if s < stamp_ns and e == self._frame_epoch]:
            self._truth_unused(stamp, self._truth.pop(stamp)[0])

    def _truth_unused(self, stamp_ns: int, epoch: int) -> bool:
        """Count a ground-truth message that goes without scoring a frame as matching no
        frame (report ``gt_unmatched``, its stamp among the first few listed), unless a frame
        of its stamp and epoch was processed (a second message of that stamp). Returns whether
        it was counted."""
        if (stamp_ns, epoch) in self._processed:
            return False
        self.counts['gt_unmatched'] = self.counts.get('gt_unmatched', 0) + 1
        listed = self.report.gt_unmatched_stamps
        if len(listed) < MAX_LISTED_UNMATCHED_TRUTH:
            listed.append(int(stamp_ns))
        return True

    def _truth_found(self, stamp_ns: int, epoch: int) -> None:
        """A frame of ``stamp_ns`` came after its ground truth was dropped for waiting too
        long: that ground truth did match a frame, so it no longer counts as matching none."""
        if self._truth_dropped.get(stamp_ns, -1) != epoch:
            return
        self._truth_dropped[stamp_ns] = None
        self.counts['gt_unmatched'] -= 1
        with contextlib.suppress(ValueError):
            self.report.gt_unmatched_stamps.remove(stamp_ns)

    def add_result(self, result: FrameResult) -> None:
        """Offer a processed frame; scored now if its ground truth is known, can no longer
        come (ground truth of a later stamp was read) or the bag has none, else held until it
        comes (see the class)."""
        self.counts['processed'] += 1
        if self.plan.ground_truth is None:
            self._score(result, None)
            return
        stamp = result.stamp_ns
        epoch = self.frame_epoch(stamp)
        held = self._truth_held
        if held is not None and held[0] == stamp and epoch == self._truth_epoch:
            # Its ground truth came out of order, before it: not the first after a jump.
            self._release_truth(jumped=False)
        _remember(self._processed, (stamp, epoch))
        self._truth_found(stamp, epoch)
        truth = self._truth.pop(stamp, None)
        if truth is not None and truth[0] < epoch:
            # Ground truth of this stamp from before a jump back whose frame never took it (a
            # skipped frame, a second message of one stamp): not this frame's.
            self._truth_unused(stamp, truth[0])
            truth = None
        if truth is None and not any(s - stamp >= TRUTH_JUMP_NS and e == epoch
                                     for s, (e, _) in self._truth.items()):
            earlier = self._pending.pop(stamp, None)
            if earlier is not None:
                # A frame of this stamp (from before a jump back) still waits: which ground
                # truth is whose can no longer be told.
                jumped = ' the stamps jumped back and' if earlier[0] != epoch else ''
                self._score(earlier[1], None, note=(
                    f'no ground truth with this stamp before{jumped} a later frame came with '
                    'the same stamp'
                ))
            self._pending[stamp] = (epoch, result)
            while len(self._pending) > GT_WAIT_FRAMES:
                oldest, (old_epoch, frame) = self._pending.popitem(last=False)
                _remember(self._given_up, oldest, old_epoch)
                self._score(
                    frame, None, note=f'no ground truth before {GT_WAIT_FRAMES} later frames '
                    'came (ground truth later than that is not waited for)'
                )
            return
        # Ground truth of this or a later stamp was read: waiting frames of its epoch older by
        # TRUTH_JUMP_NS or more get none.
        self._give_up_before(stamp, epoch if truth is None else truth[0])
        msg = None if truth is None else truth[1]
        self._score(result, msg, note='' if msg is not None else self._no_truth(stamp))

    def frame_epoch(self, stamp_ns: int) -> int:
        """The ordering epoch of a frame of ``stamp_ns``, the next one where it goes back
        (see the class). :meth:`add_result` calls it; a caller that pairs the inputs itself
        calls it for the frames it skips too, so that a jump is seen where they lie."""
        if self._last_frame is not None and stamp_ns < self._last_frame:
            self._frame_epoch += 1
        self._last_frame = stamp_ns
        if self._truth_held is not None and self._frame_epoch > self._truth_epoch:
            # The frames jumped back where the held ground truth went back: so did it.
            self._release_truth(jumped=True)
        return self._frame_epoch

    def _give_up_before(self, stamp_ns: int, epoch: int, window: int = TRUTH_JUMP_NS) -> None:
        """Score the waiting frames of ``epoch`` that are ``window`` or more older than
        ``stamp_ns`` without ground truth (theirs can come a little after a later one: a
        ground-truth node whose latency varies reorders neighbouring messages)."""
        for stamp in [s for s, (e, _) in self._pending.items()
                      if stamp_ns - s >= window and e == epoch]:
            self._score(self._pending.pop(stamp)[1], None, note=self._no_truth(stamp))

    def _no_truth(self, stamp_ns: int, stopped: bool = False) -> str:
        """Why the frame of ``stamp_ns`` has no ground truth, in words."""
        if stamp_ns in self._truth_dropped:
            return (
                f'its ground truth came {self.truth_window} or more ground-truth messages '
                'before it and was not kept'
            )
        if stopped:
            note = 'no ground truth with this stamp read before the run stopped'
        else:
            note = 'no ground truth with this stamp in the bag'
        if self._unreadable_truth:
            # Its own may be one of them: their stamps cannot be read.
            count = self._unreadable_truth
            note += (f' ({count} ground-truth message{"s" if count > 1 else ""} could not be '
                     'read)')
        return note

    def _ground_truth(self, result: FrameResult, msg: Any) -> tuple[np.ndarray | None, str]:
        """The frame's ground truth at the processed resolution, or None and why.

        A ``DisparityImage`` holds d + Δ with the Δ of its own resolution: the input's for
        one at the input size (shrunk here like the data sets), the processed one's for one
        at the output size already, i.e. Δ of the geometry scaled as the node scales it
        (``result.geometry``; Δ/downsample without one).
        """
        shape = result.disparity.shape
        factor = self.options.pipeline.downsample
        offset = result.offset
        inner = getattr(msg, 'image', msg)
        if factor > 1 and (int(inner.height), int(inner.width)) == shape:
            offset = (result.offset / factor if result.geometry is None
                      else result.geometry.disparity_offset)
        try:
            gt = disparity_from_msg(msg, offset, self.plan.ground_truth or 'ground truth')
        except InputError as err:
            return None, f'bad ground truth: {err}'
        if gt.shape == shape:
            return gt, ''
        source = result.input_shape
        if factor > 1 and (
            gt.shape == tuple(source) if source is not None
            else (gt.shape[0] // factor, gt.shape[1] // factor) == shape
        ):
            # The data sets' NaN-aware block mean, values divided by the factor too; the rest
            # of an odd size is cropped, as the pipeline crops the input.
            from cva_confidence_ros.datasets import resize_disparity

            shrunk = resize_disparity(gt, factor)
            if shrunk.shape == shape:
                return shrunk, ''
        size = f'ground truth is {gt.shape[1]}×{gt.shape[0]} but the'
        if factor == 1 or source is None:
            return None, f'{size} output is {shape[1]}×{shape[0]} (downsample {factor})'
        return None, (
            f'{size} input is {source[1]}×{source[0]} (the output {shape[1]}×{shape[0]} at '
            f'downsample {factor})'
        )

    def _score(self, result: FrameResult, msg: Any | None, note: str = '') -> None:
        # Scoring and the frame's PNGs are quick; keeping a signal out of them means a report
        # never lists a frame whose plots were cut off.
        with self.interrupts.critical():
            self._score_now(result, msg, note)

    def _score_now(self, result: FrameResult, msg: Any | None, note: str) -> None:
        from cva_confidence_ros.confidence import is_probabilistic

        gt = None
        if msg is not None:
            gt, note = self._ground_truth(result, msg)
        def score_against(truth: np.ndarray | None) -> FrameScore:
            return score_frame(
                result.frame, result.stamp_ns, result.disparity, result.confidence,
                result.kept, truth, max_pixels=self.options.max_pixels, seed=self.options.seed,
                probabilistic=is_probabilistic(self.options.pipeline.confidence_method),
                region=result.region,
            )

        try:
            score = score_against(gt)
        except InputError as err:
            note = f'not scored: {err}'
            score = FrameScore(frame=result.frame, stamp_ns=result.stamp_ns)
            if gt is not None:
                # What needs no ground truth (kept share, predicted error, mean confidence)
                # is still the frame's: only the scoring against it failed.
                with contextlib.suppress(InputError):
                    score = score_against(None)
        else:
            if gt is not None and self.options.scan is not None and result.geometry is not None:
                self._score_scan(score, result, gt)
        if note:
            score.note = note
        if score.auc is None and self.plan.ground_truth is not None:
            self._log_unscored(score)
        score.processing_ms = result.processing_ms
        score.latency_ms = result.latency_ms
        self.report.frames.append(score)
        if self.writer is not None:
            self.writer.frame_plots(
                score, result.confidence, self.options.pipeline.confidence_method,
                kept=result.kept, image=result.image,
            )

    def _score_scan(self, score: FrameScore, result: FrameResult, gt: np.ndarray) -> None:
        """Score the frame's laser scan: that of its kept pixels with ground truth against the
        ground truth's scan of the same pixels (``scan.score_scan``)."""
        from cva_confidence_ros.scan import disparity_to_scan, score_scan

        config, geometry = self.options.scan, result.geometry
        assert config is not None and geometry is not None  # the caller checked
        known = np.isfinite(gt)
        try:
            truth = disparity_to_scan(gt, geometry, known, None, config)
            scan = disparity_to_scan(
                result.disparity, geometry, result.kept & known, result.confidence, config
            )
            scored = score_scan(scan, truth, geometry, config)
        except InputError:
            return  # the scan itself was written; the frame just has no scan score
        score.scan_beams = scored.beams
        score.scan_phantom_rate = scored.rate('phantom')
        score.scan_far_rate = scored.rate('far')
        score.scan_none_rate = scored.rate('none')

    def _log_unscored(self, score: FrameScore) -> None:
        """Say why a frame of a bag with ground truth has no metrics (throttled per reason)."""
        kind = score.note.split(':', 1)[0] or 'no metrics'
        self._unscored_logs[kind] += 1
        count = self._unscored_logs[kind]
        if count <= _MAX_UNSCORED_LOGS:
            self.log(f'frame {score.frame} (stamp {score.stamp_ns} ns) not scored: {score.note}')
        elif count == _MAX_UNSCORED_LOGS + 1:
            self.log(f'more frames not scored for "{kind}"; only counting them from now on')

    def stop_pairing(
        self, sync: Any, bag: InputBag, since_ns: int | None, store: Any
    ) -> None:
        """End the pairing of a run however it stopped: the messages still waiting for
        partners are let go and listed (after the end of the bag there are none left), so
        that the count and the list agree; after a Ctrl-C the ground truth of the frames still
        waiting is looked for further on in ``bag`` (from ``since_ns``)."""
        with self.interrupts.critical():
            sync.drain()
            self.report_drops(sync, stopped=True)
        self.counts['unpaired'] = sync.dropped
        if self.interrupts.requested:
            self.read_ahead_ground_truth(bag, since_ns, store)

    def read_ahead_ground_truth(self, bag: InputBag, since_ns: int | None, store: Any) -> None:
        """Look further into ``bag`` for the ground truth of frames still waiting for it.

        A replay stopped early (Ctrl-C) has processed frames whose ground truth lies a little
        later in the bag; they are scored rather than reported without metrics. Reads the
        ground-truth topic only, from bag time ``since_ns``, and at most a few messages more
        than frames wait. A bag that fails here is left to what was already read.
        """
        if not self._pending or self.plan.ground_truth is None or since_ns is None:
            return
        from rosbags.serde import SerdeError

        budget = 2 * len(self._pending) + 4
        try:
            for _, msgtype, _, raw in bag.messages([self.plan.ground_truth], start=since_ns):
                budget -= 1
                try:
                    msg = store.deserialize_cdr(raw, msgtype)
                except SerdeError:
                    continue
                stamp = stamp_to_ns(msg.header.stamp)
                if stamp in self._pending:
                    self.add_ground_truth(stamp, msg)
                if not self._pending or budget <= 0:
                    return
        except BagError:
            return

    def finish(self) -> None:
        """Score what still waits, close the output bag, write the report.

        The bag is closed even if scoring fails, so that what was written stays readable. A
        bag that cannot be finished, or a frame's PNGs that cannot be written (a full disk), is
        recorded as the run's error, and the report of the frames done is written all the same
        (a PNG error is raised after it).
        """
        stopped = self.report.interrupted or bool(self.report.error)
        failure: ConfigError | None = None
        try:
            # The last ground truth went back a little and nothing came after it.
            self._release_truth()
            while self._pending:
                stamp, (_, result) = self._pending.popitem(last=False)
                try:
                    self._score(result, None, note=self._no_truth(stamp, stopped))
                except ConfigError as err:
                    # A PNG that cannot be written (a full disk; no more are tried): the frame
                    # is in the report, and the report is written with the error all the same.
                    failure = failure or err
                    self.report.error = '; '.join(filter(None, (self.report.error, str(err))))
            # Ground truth still waiting matched no frame; after an early stop only that which
            # the frames have passed (the rest may be of frames further on in the bag).
            for stamp, (epoch, _) in self._truth.items():
                if not stopped or epoch < self._frame_epoch or (
                    epoch == self._frame_epoch and self._last_frame is not None
                    and stamp < self._last_frame
                ):
                    self._truth_unused(stamp, epoch)
            self._truth.clear()
        finally:
            if self.out is not None:
                try:
                    self.out.close()
                except BagError as err:
                    self.report.error = '; '.join(filter(None, (self.report.error, str(err))))
                else:
                    if not (self.out.kept_old or self.out.dropped_empty):
                        self.paths['bag'] = Path(self.options.out)
        if self.writer is not None:
            self.paths.update(self.writer.write(self.report))
        if failure is not None:
            raise failure

    def outcome(self) -> ReplayOutcome:
        """Exit code and closing message of the run (call after leaving the context)."""
        counts = self.counts
        done = counts['processed']
        if self.out is not None and self.out.kept_old:
            bag = (
                f'the existing output bag {self.options.out} was left as it was (nothing written)'
            )
        elif self.out is not None and self.out.dropped_empty:
            bag = f'no output bag written (nothing to write at {self.options.out})'
        elif self.out is not None and self.out.lost:
            bag = f'no output bag (its storage lost the frames; nothing at {self.options.out})'
        else:
            bag = f'output bag {self.options.out}'
        where = f'{bag}, report {self.paths.get("json", self.options.report)}'
        if self.report.interrupted:
            # Live mode: frames the node may still have been working on are no dropped ones.
            flying = counts.get('in_flight', 0)
            waiting = f' ({flying} more were still on their way)' if flying else ''
            return ReplayOutcome(
                self.report, self.paths, 130,
                f'interrupted after {done} frames{waiting}; {where} hold them' if done
                else f'interrupted before the first frame{waiting}; {where}',
            )
        if self.report.error:
            return ReplayOutcome(
                self.report, self.paths, 2,
                f'{self.report.error}; {done} frames were done before ({where})',
            )
        if done == 0:
            empty = [topic for topic, n in self.plan.input_counts.items() if n == 0]
            if counts['pairs'] == 0 and empty:
                where_in = 'bag'
                if self.plan.window != (None, None):
                    # The counts are the window's: "no messages in bag X" of a bag full of
                    # them sent users to check their recording.
                    span = ('to its end' if self.options.duration_s is None
                            else f'for {self.options.duration_s:g} s')
                    where_in = (f'the part replayed (from {self.options.start_s:g} s {span}) '
                                f'of bag')
                reason = (
                    f'the input topic{"s" if len(empty) > 1 else ""} {", ".join(empty)} '
                    f'hold{"" if len(empty) > 1 else "s"} no messages in {where_in} '
                    f'{self.options.bag}: there is nothing to pair'
                )
            elif counts['pairs'] == 0:
                reason = (
                    'no stereo pair matched by stamp: left/right images and camera infos '
                    'must share header stamps (or use --approximate-sync with '
                    f'--sync-tolerance); {counts["unpaired"]} messages stayed unpaired'
                    f'{self._unpaired_text()}'
                )
                if counts.get('unreadable'):
                    reason += (
                        f'; {counts["unreadable"]} input messages could not be read (see the '
                        'messages above)'
                    )
            elif counts['skipped']:
                reason = (
                    f'none of the {counts["pairs"]} stereo pairs could be processed '
                    f'({counts["skipped"]} skipped, see the messages above)'
                )
            else:
                from cva_confidence_ros.ros.common import (
                    LARGE_MESSAGES_HINT,
                    large_messages_unset,
                )

                reason = f'the node answered none of the {counts["pairs"]} stereo pairs'
                if counts.get('unreadable'):
                    # Live mode: the node's outputs may have come, unreadable (cut short).
                    reason += (
                        f'; {counts["unreadable"]} messages could not be read (see the '
                        'messages above)'
                    )
                if self.options.mode == 'live' and large_messages_unset():
                    reason += f' ({LARGE_MESSAGES_HINT})'
            return ReplayOutcome(self.report, self.paths, 2, f'{reason} ({where})')
        summary = self.report.summary()
        text = (
            f'{done} of {counts["pairs"]} frames processed, {counts["skipped"]} skipped, '
            f'{counts["dropped"]} dropped, {counts["unpaired"]} unpaired messages'
            f'{self._unpaired_text()}'
        )
        if counts.get('unreadable'):
            text += f', {counts["unreadable"]} unreadable messages'
        if summary['kept_fraction'] is not None:
            text += (
                f"; kept {100 * summary['kept_fraction']:.1f} % of the pixels (least "
                f"{100 * summary['min_kept_fraction']:.1f} % in frame "
                f"{summary['min_kept_fraction_frame']})"
            )
            if summary['predicted_kept_error'] is not None:
                text += (
                    f", predicted error of the kept {100 * summary['predicted_kept_error']:.1f} %"
                )
        if summary['auc'] is not None:
            text += (
                f"; mean AUC ×100 {100 * summary['auc']:.2f} "
                f"(opt {100 * summary['auc_opt']:.2f}), "
                f"error rate {100 * summary['error_rate']:.2f} %"
            )
        if summary['scan_beams']:
            text += (
                f"; scan: {100 * summary['scan_phantom_rate']:.1f} % phantom beams of "
                f"{summary['scan_beams']} against the ground truth's"
            )
        scored = summary['frames_scored']
        if self.plan.ground_truth is not None and scored < len(self.report.frames):
            reasons = list(self.report.not_scored().items())
            listed = '; '.join(
                f'{note} ({n} frame{"s" if n > 1 else ""})' for note, n in reasons[:3]
            )
            more = f'; {len(reasons) - 3} more reasons in the report' if len(reasons) > 3 else ''
            text += (
                f'; {scored} of {len(self.report.frames)} frames scored (ground truth '
                f'unusable: {listed}{more})'
            )
        text += self._unmatched_truth_text()
        return ReplayOutcome(self.report, self.paths, 0, f'{text}; {where}')

    def _unmatched_truth_text(self) -> str:
        """``; n ground-truth messages matched no processed frame (stamps ...)``, or ''."""
        count = self.counts.get('gt_unmatched', 0)
        if not count:
            return ''
        stamps = self.report.gt_unmatched_stamps[:2]
        text = (f'; {count} ground-truth message{"s" if count > 1 else ""} on '
                f'{self.plan.ground_truth} matched no processed frame')
        if stamps:
            more = ', …' if count > len(stamps) else ''
            text += f' (stamp{"s" if count > 1 else ""} {", ".join(map(str, stamps))}{more} ns'
            if self._processed and stamps[0] not in self._skipped:
                # A constant offset (ground truth stamped at another time) shows here.
                nearest = min((s for s, _ in self._processed), key=lambda s: abs(s - stamps[0]))
                if nearest != stamps[0]:
                    text += (f'; {stamps[0]} is {_offset(stamps[0] - nearest)} than frame '
                             f'stamp {nearest}')
            text += ')'
        listed = self.report.gt_unmatched_stamps
        skipped = sum(stamp in self._skipped for stamp in listed)
        if listed and skipped == len(listed) == count:
            # A camera_info of another size, say, skipped the frames: their ground truth is
            # stamped right, and "must carry its left image's stamp" sent users to the wrong
            # place.
            return text + (': the stereo pairs of those stamps were skipped (bad frames, see '
                           'above)')
        hint = f'{skipped} of those listed are stamps of skipped frames; ' if skipped else ''
        return text + (f': no stereo pair of that stamp was processed ({hint}ground truth must '
                       "carry its left image's stamp)")

    def _unpaired_text(self) -> str:
        """`` (topic: n, ...)`` of the unpaired messages per topic, or ''."""
        by_topic = self.report.unpaired_by_topic
        if not by_topic:
            return ''
        return ' (' + ', '.join(f'{t}: {n}' for t, n in sorted(by_topic.items())) + ')'


def _remember(stamps: OrderedDict[Any, Any], stamp_ns: Any, value: Any = None) -> None:
    """Add a stamp (→ ``value``) to a bounded record of stamps (the oldest goes)."""
    stamps[stamp_ns] = value
    while len(stamps) > _MAX_REMEMBERED:
        stamps.popitem(last=False)


def check_output_bag_folder(out: str | Path) -> None:
    """Check that the output bag can be created at ``out``: make its parent folders and try
    writing there (where the bag, or the staging folder that replaces an old one, goes).

    Raises:
        ConfigError: A file is in the way, or the folder cannot be written.
    """
    try:
        check_output_dir(Path(out).absolute().parent, 'the folder')
    except ConfigError as err:
        raise ConfigError(f'cannot create output bag {out}: {err}') from None


def _offset(delta_ns: int) -> str:
    """A stamp difference in words: ``5 µs later``, ``2.5 ms earlier``."""
    size = abs(delta_ns)
    unit, scale = next(
        ((unit, scale) for unit, scale in (('s', 10**9), ('ms', 10**6), ('µs', 10**3))
         if size >= scale),
        ('ns', 1),
    )
    value = f'{size / scale:.3f}'.rstrip('0').rstrip('.')
    return f'{value} {unit} {"later" if delta_ns > 0 else "earlier"}'



# Modules the frames need later, imported before the first frame: a Ctrl-C that lands inside
# an import leaves a half-initialised module behind, which would break the report written after.
_PRELOAD = (
    'matplotlib.backends.backend_agg',
    'matplotlib.figure',
    'cva_confidence_ros.plots',
    'cva_confidence_ros.metrics',
    'cva_confidence_ros.evaluation',
    'cva_confidence_ros.datasets',
    'cva_confidence_ros.pointcloud',
    'cva_confidence_ros.ros.convert',
    'cva_confidence_ros.ros.transport',
    'cva_confidence_ros.ros.confidence_node',
    'cv2',
    'rclpy.serialization',
    'rosbags.serde',
)


def preload() -> None:
    """Import every module a replay uses lazily (see ``_PRELOAD``)."""
    for name in _PRELOAD:
        importlib.import_module(name)


def make_synchronizer(options: ReplayOptions) -> Any:
    """The node's stamp synchroniser with the run's sync options."""
    from cva_confidence_ros.sync import StampSynchronizer

    return StampSynchronizer(
        keys=INPUT_KEYS,
        queue_size=options.queue_size,
        approximate=options.approximate_sync,
        tolerance_ns=int(round(options.sync_tolerance_s * 1e9)),
        record_drops=True,
    )


def run_offline(
    options: ReplayOptions,
    log: Logger = log_stderr,
    interrupts: GracefulInterrupt | None = None,
) -> ReplayOutcome:
    """Replay a bag through the pipeline as fast as possible (deterministic).

    A Ctrl-C stops the run after the frame in hand (a second one at once); the frames done
    are in the outputs.

    Args:
        options: The run's options (``mode`` is not looked at).
        log: Receives one-line messages (skips, notes).
        interrupts: The caller's Ctrl-C handling, if it has begun one; else the run's own.

    Returns:
        The :class:`ReplayOutcome`; faults after the start (corrupt data part-way, Ctrl-C,
        every frame bad) end the run with the outputs closed and a non-zero exit code.

    Raises:
        BagError: The bag cannot be opened or lacks an input topic (nothing is written).
        ConfigError, ModelError: The pipeline cannot be built, or the report folder cannot be
            created (nothing is written).
    """
    from rosbags.serde import SerdeError

    from cva_confidence_ros.pipeline import StereoPipeline

    interrupts = interrupts or GracefulInterrupt(notice=STOPPING)
    with interrupts, InputBag(options.bag) as bag:
        store = jazzy_typestore()
        preload()
        plan = plan_topics(bag, options, log)
        pipeline = StereoPipeline(options.pipeline, mask_option='--mask')
        interrupts.check()
        sync = make_synchronizer(options)
        key_of = plan.key_of
        progress = Progress(plan.pairs_expected, prefix='[cva-bag-replay] offline: ')
        session = ReplaySession(options, plan, log, interrupts=interrupts)
        position: int | None = None  # bag time of the last message read
        with session, progress:
            try:
                for topic, msgtype, timestamp, raw in bag.messages(plan.topics, *plan.window):
                    interrupts.check()
                    position = timestamp
                    try:
                        msg = store.deserialize_cdr(raw, msgtype)
                    except SerdeError as err:
                        session.unreadable(topic, timestamp, err)
                        continue
                    stamp = stamp_to_ns(msg.header.stamp)
                    if topic == plan.ground_truth:
                        session.add_ground_truth(stamp, msg)
                        continue
                    for matched in sync.add(key_of[topic], stamp, (msg, timestamp)):
                        frame = session.counts['pairs']
                        session.counts['pairs'] += 1
                        _process_pair(session, pipeline, matched, frame)
                        progress.update()
                    session.report_drops(sync)
                sync.drain()
                session.report_drops(sync)
                if plan.window[1] is not None:
                    # The ground truth of the last frames may lie just past the part replayed.
                    session.read_ahead_ground_truth(bag, plan.window[1], store)
            finally:
                session.stop_pairing(sync, bag, position, store)  # also on Ctrl-C, a bag fault
    return session.outcome()


def _process_pair(session: ReplaySession, pipeline: Any, matched: Any, frame: int) -> None:
    options = session.options
    items = {key: value[0] for key, value in matched.items.items()}
    timestamp = int(matched.items['left'][1])
    session.frame_epoch(matched.stamp_ns)  # a jump back, even where this frame is skipped
    try:
        left, right, geometry = stereo_inputs(items)
        result = pipeline.process(left, right)
    except CVAError as err:
        # As the node does: whatever the pipeline refuses for one frame's data (bad images,
        # or a frame narrower than max_disparity, a ConfigError) drops that frame only.
        session.skip(f'frame {frame} (stamp {matched.stamp_ns} ns)', err, matched.stamp_ns)
        return
    outputs = node_outputs(
        result, geometry, left.shape[:2], items['left'].header, options.pipeline,
        publish_points=options.publish_points, points_organized=options.points_organized,
        points_confidence=options.points_confidence, publish_depth=options.publish_depth,
        depth_encoding=options.depth_encoding, publish_overlay=options.publish_overlay,
        compressed=options.compressed, scan=options.scan, scan_frame_id=options.scan_frame_id,
        left_info=items['left_info'],
    )
    topics = options.topics.outputs()
    shown = result.left
    # The frame's messages and its line in the report go together, whenever the signal comes.
    with session.interrupts.critical():
        session.write(
            [(topics[name], kind, data) for name, kind, data in outputs.messages], timestamp
        )
        session.add_result(
            FrameResult(
                frame=frame,
                stamp_ns=matched.stamp_ns,
                disparity=result.disparity,
                confidence=outputs.confidence,
                kept=outputs.kept,
                offset=geometry.disparity_offset,
                processing_ms=float(result.timings_ms.get('total', 0.0)),
                # Not the whole result: a frame may wait a while for its ground truth.
                image=lambda: shown,
                region=result.region,
                geometry=outputs.geometry,
                input_shape=(int(left.shape[0]), int(left.shape[1])),
            )
        )
