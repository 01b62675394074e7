"""``cva-bag-replay``: run a stereo bag through the node's pipeline and score its confidence.

Reads a rosbag2 (MCAP or sqlite3, any compression ``rosbags`` reads), pairs left/right images
and camera infos by stamp with the node's synchroniser, runs the node's pipeline (matcher,
confidence method, weights, downsample, threshold), and writes

* an output bag with what the node publishes (``disparity``, ``confidence``, ``points2``,
  ``disparity_filtered``, ``depth``, ``camera_info``), stamped like the input; with
  ``--compressed``, ``depth`` and the overlay as image_transport's ``depth/compressedDepth``
  and ``confidence_overlay/compressed`` (the node's encoders and parameters), a fraction of
  the size;
* where the bag has ground truth: ``DIR/report.json`` (``frames``: records with ``frame``,
  ``stamp_ns``, ``error_rate``, ``auc``, ``auc_opt``, ``kept_density``, ``kept_error_rate``;
  ``summary``: their means and the frame counters), ``DIR/report.csv``, ``DIR/summary.md`` and
  PNGs (confidence maps, ROC curves, AUC over time).

An existing output bag, or a report folder that holds an earlier report, is refused before any
work unless ``--overwrite`` is given; then the old report's files are deleted (nothing else in
the folder), and the old bag is replaced only once the new one holds a frame (an output folder
that a killed or disk-full run left without its ``metadata.yaml`` is replaced too). Input messages
that pair with nothing (a stamp off by a few µs, a duplicate stamp) and frames whose ground
truth is unusable are named on stderr (the first few) and listed in the report.

Modes: ``offline`` processes as fast as it can (deterministic); ``live`` plays the bag over DDS
to the node (started as a subprocess with the same parameters, or a running one with
``--no-start-node``) at the recorded speed times ``--rate-scale`` and records what it
publishes, dropped frames included.

Exit codes: 0 done, 2 bad input or a fault that stopped the run (one line on stderr), 130
interrupted by Ctrl-C, 143 by SIGTERM (the outputs hold the frames done).

Example::

    cva-bag-replay motorcycle_bag --out replay_bag --report replay --downsample 2
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys

from cva_confidence_ros.errors import ConfigError, CVAError, from_interrupt
from cva_confidence_ros.mask import load_mask
from cva_confidence_ros.matching.subpixel import SUBPIXEL_METHODS
from cva_confidence_ros.pipeline import PipelineConfig
from cva_confidence_ros.scan import ScanConfig
from msg_tools.bagio import STORAGES
from msg_tools.progress import GracefulInterrupt
from msg_tools.replay import STOPPING, CompressionConfig, ReplayOptions, TopicNames

#: ``--sync-tolerance`` unless given: the node's ``approximate_sync_tolerance_seconds`` default.
SYNC_TOLERANCE_S = 0.01

__all__ = ['build_parser', 'main', 'name_options', 'options_from_args']

_DEFAULTS = PipelineConfig.__dataclass_fields__
_SCAN = ScanConfig()
_COMPRESSION = CompressionConfig.__dataclass_fields__  # defaults without importing rclpy
#: The compression options: node parameter (and argparse dest) → option.
_COMPRESSION_OPTIONS = {
    'overlay_jpeg_quality': '--jpeg-quality',
    'compressed_depth_max': '--compressed-depth-max',
    'compressed_depth_quantization': '--compressed-depth-quantization',
    'compressed_depth_png_level': '--compressed-depth-png-level',
}
#: Every name under which a configuration error (``ConfigError.fields``) can name a value the
#: command line sets → its option, to name what the user typed: the fields of ReplayOptions,
#: TopicNames and PipelineConfig, and the node parameters live mode sets (the scan's included).
_FIELD_OPTIONS = {
    'mode': '--mode',
    'storage': '--storage',
    'queue_size': '--queue-size',
    'sync_tolerance_s': '--sync-tolerance',
    'max_pixels': '--max-pixels',
    'max_plots': '--max-plots',
    'seed': '--seed',
    'rate_scale': '--rate-scale',
    'startup_timeout_s': '--startup-timeout',
    'drain_timeout_s': '--drain-timeout',
    'start_s': '--start',
    'duration_s': '--duration',
    'prefix': '--topic-prefix',
    'left': '--left-topic',
    'right': '--right-topic',
    'left_info': '--left-info-topic',
    'right_info': '--right-info-topic',
    'ground_truth': '--gt-topic',
    'matcher': '--matcher',
    'confidence_method': '--confidence-method',
    'model_path': '--weights',
    'max_disparity': '--max-disparity',
    'downsample': '--downsample',
    'confidence_threshold': '--confidence-threshold',
    'device': '--device',
    'lr_check': '--lr-check',
    'subpixel': '--subpixel',
    'speckle_size': '--speckle-size',
    'speckle_range': '--speckle-range',
    'tile_budget_mb': '--tile-budget-mb',
    'roi_top': '--roi',
    'roi_bottom': '--roi',
    'mask_path': '--mask',
    'approximate_sync': '--approximate-sync',
    'approximate_sync_tolerance_seconds': '--sync-tolerance',
    'publish_points': '--no-points',
    'points_organized': '--points-unorganized',
    'points_confidence': '--points-confidence',
    'publish_depth': '--no-depth',
    'publish_overlay': '--overlay',
    'depth_encoding': '--depth-encoding',
    'publish_scan': '--scan',
    'scan_frame_id': '--scan-frame-id',
    'scan_min_height': '--scan-height',
    'scan_max_height': '--scan-height',
    'scan_range_min': '--scan-range',
    'scan_range_max': '--scan-range',
    'scan_pitch': '--scan-pitch',
    **_COMPRESSION_OPTIONS,
}


def _default(name: str) -> object:
    return _DEFAULTS[name].default


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``cva-bag-replay``."""
    parser = argparse.ArgumentParser(
        prog='cva-bag-replay',
        description='Replay a stereo rosbag2 through the CVA confidence pipeline; write an '
        'output bag and a per-frame confidence report.',
        epilog='Exit codes: 0 done, 2 bad input or a fault that stopped the run (one line on '
        'stderr), 130 interrupted by Ctrl-C, 143 by SIGTERM (the output bag and the report '
        'hold the frames done).',
    )
    parser.add_argument('bag', type=Path, help='input bag (folder, .mcap or .db3)')
    parser.add_argument('--out', type=Path, required=True, help='output bag folder to create')
    parser.add_argument('--report', type=Path, required=True,
                        help='report folder (refused while another cva-bag-replay writes '
                        'into it, --overwrite or not)')
    parser.add_argument('--mode', choices=('offline', 'live'), default='offline',
                        help='offline: as fast as possible; live: over DDS to the node')

    part = parser.add_argument_group('part of the bag (bag time, both modes)')
    part.add_argument('--start', type=float, default=0.0, metavar='SECONDS',
                      help="replay from this many seconds after the bag's first message "
                           '(as ros2 bag play --start-offset; default 0)')
    part.add_argument('--duration', type=float, default=None, metavar='SECONDS',
                      help='replay this many seconds from there (default: to the end)')
    node = parser.add_argument_group('pipeline (the node parameters of the same names)')
    node.add_argument('--matcher', default=_default('matcher'), help='census_bm, census_sgm, '
                      'mccnn_fast (default %(default)s)')
    node.add_argument('--confidence-method', default=_default('confidence_method'),
                      help='any confidence_method of the node: cva_net, cva_net_fast, '
                           'cva_net_lite, ccnn, lfn, lgc_net or a hand-crafted measure '
                           '(default %(default)s)')
    node.add_argument('--weights', default=_default('model_path'),
                      help='CVA-Net weights (default: the shipped ones for the matcher)')
    node.add_argument('--max-disparity', type=int, default=_default('max_disparity'),
                      help='cost-volume depth D (default %(default)s)')
    node.add_argument('--downsample', type=int, default=_default('downsample'),
                      help='process at 1/K resolution, K in 1, 2, 4 (default %(default)s)')
    node.add_argument('--confidence-threshold', type=float,
                      default=_default('confidence_threshold'),
                      help='pixels below it are dropped from the filtered outputs')
    node.add_argument('--device', default=_default('device'), help='cpu, cuda or auto')
    node.add_argument('--lr-check', action='store_true', help='left-right consistency check')
    node.add_argument('--subpixel', choices=SUBPIXEL_METHODS, default=_default('subpixel'),
                      help='sub-pixel disparity: equiangular, parabola or none (integer '
                           'disparities); default %(default)s')
    node.add_argument('--speckle-size', type=int, default=_default('speckle_size'),
                      help='drop kept regions of at most this many pixels (0 = off; default '
                           '%(default)s)')
    node.add_argument('--speckle-range', type=float, default=_default('speckle_range'),
                      help='largest disparity step within one such region, px (default '
                           '%(default)s)')
    node.add_argument('--tile-budget-mb', type=float, default=_default('tile_budget_mb'),
                      help='memory budget of one network tile')
    node.add_argument('--roi', type=float, nargs=2, metavar=('TOP', 'BOTTOM'),
                      default=(_default('roi_top'), _default('roi_bottom')),
                      help='process only the rows from TOP to BOTTOM, as shares of the image '
                           'height (roi_top, roi_bottom; default %(default)s = all)')
    node.add_argument('--mask', type=Path, default=None, metavar='PNG',
                      help="ignore mask of the input size, black where the camera sees the "
                           "robot's own body (mask_path): nothing kept there, and the kept "
                           'share is of the other pixels')
    node.add_argument('--approximate-sync', action='store_true',
                      help='pair messages whose stamps differ by at most --sync-tolerance')
    node.add_argument('--sync-tolerance', type=float, default=None, metavar='SECONDS',
                      help='approximate sync tolerance in seconds (with --approximate-sync; '
                           f"default {SYNC_TOLERANCE_S:g}, the node's "
                           'approximate_sync_tolerance_seconds)')
    node.add_argument('--queue-size', type=int, default=10, help='synchroniser queue size')
    node.add_argument('--no-points', action='store_true', help='do not write points2')
    node.add_argument('--points-unorganized', action='store_true',
                      help='points2 holds only the kept points (default: organised H×W)')
    node.add_argument('--points-confidence', action='store_true',
                      help='points2 holds every triangulated point with a float32 confidence '
                           'field (the node parameter points_confidence), for filtering later')
    node.add_argument('--no-depth', action='store_true', help='do not write depth')
    node.add_argument('--overlay', action='store_true',
                      help='also write confidence_overlay (rgb8: the kept pixels tinted red to '
                           'green by confidence over the scene), to look at in Foxglove or rviz')
    node.add_argument('--depth-encoding', choices=('32FC1', '16UC1'), default='32FC1',
                      help='depth as float metres (NaN = none) or uint16 millimetres (0 = none)')
    node.add_argument('--scan', action='store_true',
                      help='also write scan (sensor_msgs/LaserScan of the kept pixels in a '
                           'height band, for obstacle layers; the node parameter publish_scan)')
    node.add_argument('--scan-frame-id', default='',
                      help="frame of scan (x forward); default: the camera's body frame named "
                           'after its optical frame')
    node.add_argument('--scan-height', type=float, nargs=2, metavar=('MIN', 'MAX'),
                      default=(_SCAN.min_height, _SCAN.max_height),
                      help='height band of scan, metres above the camera (default %(default)s)')
    node.add_argument('--scan-range', type=float, nargs=2, metavar=('MIN', 'MAX'),
                      default=(_SCAN.range_min, _SCAN.range_max),
                      help='range limits of scan, metres (default %(default)s)')
    node.add_argument('--scan-pitch', type=float, default=_SCAN.pitch,
                      help='radians the camera looks down from level (default %(default)s)')

    compressed = parser.add_argument_group(
        'compressed outputs (each sets the node parameter its help names)'
    )
    compressed.add_argument(
        '--compressed', action='store_true',
        help="write depth as image_transport's depth/compressedDepth (16-bit PNG) and, with "
             '--overlay, the overlay as confidence_overlay/compressed (JPEG), instead of the raw '
             'images, as the node encodes them (sensor_msgs/CompressedImage; live mode records '
             "the node's compressed topics)",
    )
    compressed.add_argument(
        '--jpeg-quality', dest='overlay_jpeg_quality', type=int, metavar='Q',
        default=_COMPRESSION['overlay_jpeg_quality'].default,
        help='overlay_jpeg_quality: JPEG quality of the compressed overlay, 1-100 (default '
             '%(default)s)',
    )
    compressed.add_argument(
        '--compressed-depth-max', dest='compressed_depth_max', type=float, metavar='METRES',
        default=_COMPRESSION['compressed_depth_max'].default,
        help='compressed_depth_max: deeper pixels travel as no depth (default %(default)s)',
    )
    compressed.add_argument(
        '--compressed-depth-quantization', dest='compressed_depth_quantization', type=float,
        metavar='Q', default=_COMPRESSION['compressed_depth_quantization'].default,
        help='compressed_depth_quantization: a 32FC1 depth z comes back within about '
             'z^2 / (Q (Q + 1)) m (default %(default)s)',
    )
    compressed.add_argument(
        '--compressed-depth-png-level', dest='compressed_depth_png_level', type=int,
        metavar='LEVEL', default=_COMPRESSION['compressed_depth_png_level'].default,
        help='compressed_depth_png_level: zlib level of the compressedDepth PNG, 0-9 (default '
             '%(default)s)',
    )

    topics = parser.add_argument_group('topics (relative names are put under --topic-prefix)')
    topics.add_argument('--topic-prefix', default='', help='camera namespace, e.g. /stereo')
    topics.add_argument('--left-topic', default='left/image_rect')
    topics.add_argument('--right-topic', default='right/image_rect')
    topics.add_argument('--left-info-topic', default='left/camera_info')
    topics.add_argument('--right-info-topic', default='right/camera_info')
    topics.add_argument('--gt-topic', default=None,
                        help='ground truth (DisparityImage or 32FC1 Image); default '
                        'ground_truth/disparity, used when the bag has it')

    report = parser.add_argument_group('report')
    report.add_argument('--max-pixels', type=int, default=None,
                        help='score a fixed random subset of N ground-truth pixels per frame')
    report.add_argument('--seed', type=int, default=0, help='seed of that subset (>= 0)')
    report.add_argument('--max-plots', type=int, default=10,
                        help='frames that get confidence, overlay and ROC PNGs, spread evenly '
                             'over the bag (default %(default)s)')

    output = parser.add_argument_group('output bag')
    output.add_argument('--storage', choices=STORAGES, default='mcap',
                        help='storage of the output bag (default mcap)')
    output.add_argument('--overwrite', action='store_true',
                        help='replace an existing output bag (once the new one holds a frame; '
                        'also the folder a killed or disk-full run left without its '
                        'metadata.yaml) and the files of an earlier report in the report folder')

    live = parser.add_argument_group('live mode')
    live.add_argument('--rate-scale', type=float, default=1.0,
                      help='play at this multiple of the recorded speed')
    live.add_argument('--no-start-node', action='store_true',
                      help='connect to a running cva-node instead of starting one')
    live.add_argument('--startup-timeout', type=float, default=60.0,
                      help='seconds to wait for the node to connect')
    live.add_argument('--drain-timeout', type=float, default=30.0,
                      help='after the last input, seconds to wait without output')
    return parser


def name_options(err: ConfigError) -> ConfigError:
    """``err`` with the command-line options of its ``fields`` in front of its message.

    The library names a value by its dataclass field or node parameter (``rate_scale``,
    ``scan_min_height``); the user typed an option (``--rate-scale``, ``--scan-height``).
    Each option is named once, in the order of the fields.

    Returns:
        A new :class:`ConfigError` (``'--scan-height: scan_min_height must be ...'``), or
        ``err`` itself when it names no fields or one the command line does not set.
    """
    if not err.fields or not all(name in _FIELD_OPTIONS for name in err.fields):
        return err
    options = dict.fromkeys(_FIELD_OPTIONS[name] for name in err.fields)
    return ConfigError(f'{", ".join(options)}: {err}')


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """Turn parsed arguments into :class:`msg_tools.replay.ReplayOptions`.

    Raises:
        ConfigError: An invalid value (unknown matcher or method, range errors, ...), named
            by its option (:func:`name_options`).
    """
    try:
        return _options(args)
    except ConfigError as err:
        named = name_options(err)
        if named is err:
            raise
        raise named from None


def _options(args: argparse.Namespace) -> ReplayOptions:
    """:func:`options_from_args`, its errors named by the library's field names."""
    if args.mask is not None:
        # A missing or unreadable mask is named before any bag is opened.
        load_mask(args.mask, '--mask')
    pipeline = PipelineConfig(
        matcher=args.matcher,
        max_disparity=args.max_disparity,
        confidence_method=args.confidence_method,
        model_path=str(args.weights or ''),
        device=args.device,
        confidence_threshold=args.confidence_threshold,
        downsample=args.downsample,
        lr_check=args.lr_check,
        subpixel=args.subpixel,
        speckle_size=args.speckle_size,
        speckle_range=args.speckle_range,
        tile_budget_mb=args.tile_budget_mb,
        roi_top=args.roi[0],
        roi_bottom=args.roi[1],
        mask_path='' if args.mask is None else str(args.mask),
    )
    scan = ScanConfig(  # checked with or without --scan: a bad value is a mistake either way
        min_height=args.scan_height[0],
        max_height=args.scan_height[1],
        range_min=args.scan_range[0],
        range_max=args.scan_range[1],
        pitch=args.scan_pitch,
    )
    # Checked with or without --compressed: a bad value is a mistake either way.
    compression = CompressionConfig(**{name: getattr(args, name) for name in _COMPRESSION_OPTIONS})
    # A tolerance exact sync would ignore is refused rather than ignored.
    if args.sync_tolerance is not None and not args.approximate_sync:
        raise ConfigError(
            '--sync-tolerance needs --approximate-sync (exact sync pairs equal stamps only)'
        )
    tolerance = SYNC_TOLERANCE_S if args.sync_tolerance is None else args.sync_tolerance
    if args.scan_frame_id.startswith('/'):
        # The node refuses it too (tf2 takes no frame with a leading '/'): a scan written with
        # it could be placed by no costmap.
        raise ConfigError(
            f"--scan-frame-id must not start with '/' (tf2 refuses such frames); got "
            f'{args.scan_frame_id!r}'
        )
    topics = TopicNames(
        prefix=args.topic_prefix,
        left=args.left_topic,
        right=args.right_topic,
        left_info=args.left_info_topic,
        right_info=args.right_info_topic,
        # An empty --gt-topic is refused by name like the other topics, not taken as the
        # default (which it would then require).
        ground_truth='ground_truth/disparity' if args.gt_topic is None else args.gt_topic,
    )
    return ReplayOptions(
        bag=args.bag,
        out=args.out,
        report=args.report,
        pipeline=pipeline,
        topics=topics,
        gt_required=args.gt_topic is not None,
        mode=args.mode,
        storage=args.storage,
        approximate_sync=args.approximate_sync,
        sync_tolerance_s=tolerance if args.approximate_sync else 0.0,
        queue_size=args.queue_size,
        max_pixels=args.max_pixels,
        seed=args.seed,
        max_plots=args.max_plots,
        publish_points=not args.no_points,
        points_organized=not args.points_unorganized,
        points_confidence=args.points_confidence,
        publish_depth=not args.no_depth,
        depth_encoding=args.depth_encoding,
        publish_overlay=args.overlay,
        compressed=compression if args.compressed else None,
        scan=scan if args.scan else None,
        scan_frame_id=args.scan_frame_id,
        overwrite=args.overwrite,
        rate_scale=args.rate_scale,
        start_node=not args.no_start_node,
        startup_timeout_s=args.startup_timeout,
        drain_timeout_s=args.drain_timeout,
        start_s=args.start,
        duration_s=args.duration,
    )


def _is_ros_module(name: str) -> bool:
    """Whether ``name`` is a module of ROS 2's Python packages (rclpy, rcl_*, *_msgs, ...)."""
    root = name.split('.')[0]
    return root == 'rclpy' or root.startswith('rcl_') or root.endswith(('_msgs', '_interfaces'))


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cva-bag-replay``; returns the exit code."""
    args = build_parser().parse_args(argv)
    from cva_confidence_ros.memory import keep_freed_memory

    keep_freed_memory()
    # From here a Ctrl-C is noted and raised between steps, never inside the pipeline's or
    # rclpy's C code (see GracefulInterrupt); the imports below take a second or two.
    interrupts = GracefulInterrupt(notice=STOPPING)
    try:
        with interrupts:
            options = options_from_args(args)
            if args.mode == 'live':
                from msg_tools.live import run_live

                interrupts.check()
                outcome = run_live(options, interrupts=interrupts)
            else:
                from msg_tools.replay import run_offline

                interrupts.check()
                outcome = run_offline(options, interrupts=interrupts)
    except CVAError as err:
        if isinstance(err, ConfigError):
            # Every configuration value comes from the command line, so the node parameters
            # live mode checks (node_arguments) are named by their options too.
            err = name_options(err)
        print(f'cva-bag-replay: error: {err}', file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        # The node's parameter checks (both modes) and live mode's DDS need ROS 2's Python
        # packages: a shell without them gets one line, not a traceback.
        if not _is_ros_module(err.name or ''):
            raise
        print(f'cva-bag-replay: error: ROS 2 Python package missing ({err}); run `make setup` '
              'or source /opt/ros/jazzy/setup.bash', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, SystemError) as exc:
        # Only reached outside the replay proper (start-up, final clean-up): the output bag,
        # if one was begun, was finalised by the replay session.
        if not from_interrupt(exc):
            raise
        print('cva-bag-replay: interrupted', file=sys.stderr)
        return interrupts.exit_code
    if outcome.exit_code == 0:
        print(outcome.message)
        print('outputs: ' + ', '.join(f'{k} {v}' for k, v in sorted(outcome.paths.items())))
    elif outcome.exit_code == 130:
        print(f'cva-bag-replay: {outcome.message}', file=sys.stderr)
        return interrupts.exit_code  # 143 for SIGTERM
    else:
        print(f'cva-bag-replay: error: {outcome.message}', file=sys.stderr)
    return outcome.exit_code


if __name__ == '__main__':
    sys.exit(main())
