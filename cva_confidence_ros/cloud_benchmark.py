"""``cva-benchmark --suite cloud``: what the point clouds cost, in the node and downstream.

On the Motorcycle pair (scikit-image) at the requested size, matched by Census-BM and scored by
PKRN (the cloud stages do not depend on which), it times per frame:

* ``points2``: the node's cloud of the kept pixels (:func:`~cva_confidence_ros.pointcloud.
  stereo_cloud`) encoded as ``PointCloud2``;
* ``points2+confidence``: every point with its confidence (``points_confidence: true``);
* ``cloud_filter organised`` / ``cloud_filter dense``: what the ``cloud_filter`` node does with
  that message: decode, cut at the threshold, encode;
* ``depth 32FC1`` / ``depth 16UC1``: the node's ``depth`` image of the kept pixels (REP 118),
  computed and encoded;
* ``scan``: the node's ``LaserScan`` of the kept pixels (:func:`~cva_confidence_ros.scan.
  disparity_to_scan`, band ±0.5 m) as a message; its points are the beams with a range.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path
import statistics
import sys
import time
from typing import Any

import numpy as np

from cva_confidence_ros.benchmark import EXIT_CODES, BenchSettings, make_pairs, run_suite
from cva_confidence_ros.checks import is_real

__all__ = ['format_cloud_table', 'main', 'run_cloud']


def _median_ms(step: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    step()  # warm-up
    times, out = [], None
    for _ in range(repeat):
        tic = time.perf_counter()
        out = step()
        times.append((time.perf_counter() - tic) * 1e3)
    return statistics.median(times), out


def run_cloud(settings: BenchSettings, threshold: float) -> list[dict[str, Any]]:
    """Time the cloud stages on one frame; one record per stage.

    Returns:
        Records with ``config``, ``device``, ``width``, ``height``, ``max_disparity``,
        ``ms_per_frame`` (median of ``settings.repeat`` runs after a warm-up), ``points_in``
        and ``points_out`` (finite points before and after the stage; a scan's: beams with a
        range), ``bytes`` (message data size; a scan's: its ranges and intensities).
    """
    from std_msgs.msg import Header

    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
    from cva_confidence_ros.pointcloud import (
        StereoGeometry,
        disparity_to_depth,
        filter_cloud,
        stereo_cloud,
    )
    from cva_confidence_ros.ros.convert import (
        cloud_to_message,
        depth_image_to_array,
        depth_to_image,
        point_cloud_to_records,
        records_to_point_cloud,
        scan_to_message,
    )
    from cva_confidence_ros.scan import ScanConfig, disparity_to_scan

    left, right = make_pairs(settings)['real']
    pipeline = StereoPipeline(
        PipelineConfig(
            matcher='census_bm',
            max_disparity=settings.max_disparity,
            confidence_method='pkrn',
            confidence_threshold=threshold,
            # Kept = confidence ≥ threshold, the one rule a cloud_filter downstream can apply
            # (it sees confidences, not the node's speckle regions), so both keep the same.
            speckle_size=0,
        )
    )
    result = pipeline.process(left, right)
    height, width = result.disparity.shape
    focal = 0.8 * width
    geometry = StereoGeometry(
        fx=focal, fy=focal, cx=width / 2, cy=height / 2, cx_right=width / 2, baseline=0.1
    )
    header = Header(frame_id='left_optical')

    def node_cloud(with_confidence: bool) -> Any:
        cloud = stereo_cloud(
            result.disparity, result.confidence, result.left, geometry, result.valid,
            with_confidence=with_confidence,
        )  # fmt: skip
        return cloud_to_message(cloud, header)

    annotated = node_cloud(True)

    def filtered(organized: bool) -> Any:
        records = point_cloud_to_records(annotated)
        return records_to_point_cloud(filter_cloud(records, threshold, organized), header)

    def depth(encoding: str) -> Any:
        return depth_to_image(
            disparity_to_depth(result.disparity, geometry, result.valid), header, encoding
        )

    def scan() -> Any:
        laser = disparity_to_scan(
            result.disparity, geometry, result.valid, result.confidence,
            ScanConfig(min_height=-0.5, max_height=0.5),
        )  # fmt: skip
        return scan_to_message(laser, header)

    def finite(msg: Any) -> int:
        if hasattr(msg, 'ranges'):  # a laser scan
            return int(np.isfinite(np.asarray(msg.ranges)).sum())
        if hasattr(msg, 'encoding'):  # a depth image
            return int(np.isfinite(depth_image_to_array(msg)).sum())
        records = point_cloud_to_records(msg)
        return int(np.isfinite(records['z']).sum())

    def size(msg: Any) -> int:
        if hasattr(msg, 'ranges'):
            return 4 * (len(msg.ranges) + len(msg.intensities))
        return len(msg.data)

    stages = [
        ('points2', lambda: node_cloud(False), None),
        ('points2+confidence', lambda: node_cloud(True), None),
        ('cloud_filter organised', lambda: filtered(True), annotated),
        ('cloud_filter dense', lambda: filtered(False), annotated),
        ('depth 32FC1', lambda: depth('32FC1'), None),
        ('depth 16UC1', lambda: depth('16UC1'), None),
        ('scan', scan, None),
    ]
    records = []
    for name, step, source in stages:
        print(f'measuring {name} …', flush=True, file=sys.stderr)
        ms, msg = _median_ms(step, settings.repeat)
        records.append({
            'config': name,
            'device': 'cpu',
            'width': width,
            'height': height,
            'max_disparity': settings.max_disparity,
            'ms_per_frame': ms,
            'points_in': finite(source) if source is not None else None,
            'points_out': finite(msg),
            'bytes': size(msg),
        })  # fmt: skip
    return records


def format_cloud_table(records: Sequence[dict[str, Any]]) -> str:
    """The records as a Markdown table."""
    lines = [
        '| stage | image | ms/frame | points in | points out | message MB |',
        '|---|---|---:|---:|---:|---:|',
    ]
    for r in records:
        points_in = '—' if r['points_in'] is None else f"{r['points_in']:,}"
        lines.append(
            f"| {r['config']} | {r['width']}×{r['height']} | {r['ms_per_frame']:.2f} "
            f"| {points_in} | {r['points_out']:,} | {r['bytes'] / 1e6:.2f} |"
        )
    return '\n'.join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-benchmark --suite cloud',
        description="Milliseconds per frame of the point-cloud stages: the node's points2 "
        "with and without the confidence field, the cloud_filter node's cut, the node's "
        'depth image in both encodings and its laser scan.',
        epilog=EXIT_CODES,
    )
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--max-disparity', type=int, default=64)
    parser.add_argument('--repeat', type=int, default=20, help='timed runs per stage')
    parser.add_argument('--threshold', type=float, default=0.5,
                        help='confidence threshold of the node and the filter')
    parser.add_argument('--json', type=Path, default=None, metavar='PATH')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cva-benchmark --suite cloud``; returns the exit code."""

    def measure(args: argparse.Namespace, settings: BenchSettings) -> list[dict[str, Any]]:
        return run_cloud(settings, args.threshold)

    parser = _parser()
    args = parser.parse_args(argv)
    # Refused before run_suite makes the --json folder: a bad threshold leaves nothing behind.
    if not is_real(args.threshold) or not 0.0 <= args.threshold <= 1.0:
        parser.exit(
            2, f'cva-benchmark: error: --threshold must be in [0, 1]; got {args.threshold}\n'
        )
    return run_suite(
        parser, argv, measure, format_cloud_table, ('points_in', 'points_out', 'bytes')
    )
