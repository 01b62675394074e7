"""One-off: phantom obstacles in a laser scan from stereo, with and without the confidence.

For each scene of the develop split (KITTI 2015, Middlebury 2003, Middlebury 2014 trainingQ
Motorcycle and MotorcycleE; halved until the ground truth fits D = 64, as ``cva-evaluate``
does) and each matcher, the node's pipeline runs (CVA-Net-Fast, equiangular sub-pixel
disparity, D = 64, CPU) and ``scan.disparity_to_scan`` turns four pixel sets into laser scans:

* ``all``: every finite winner-takes-all disparity (a scan from the raw matcher);
* ``speckle``: those after the speckle filter (100 px, 1 px) alone, no confidence;
* ``node``: the node's defaults, confidence ≥ 0.5 then the speckle filter;
* ``node 0.8``: the same with ``confidence_threshold`` 0.8.

Two height bands: ``centre`` (± one eighth of the image height at the scene's median ground-
truth depth around the camera's height: a horizontal slice like ``depthimage_to_laserscan``'s
rows, in metres) and ``all heights`` (the nearest point of every column). Only pixels with
ground truth make the scans, and the ground truth's own scan (same pixels, same band) is the
reference: a beam is scored where the reference has a return. A beam's range is turned back
into a disparity along its bearing and judged by the KITTI criterion (wrong: ≥ 3 px and ≥ 5 %
off): ``phantom %`` = wrong and nearer than the truth (an obstacle that is not there, which
stops a robot or bends its path), ``far %`` = wrong and farther (the nearest thing missed),
``none %`` = no kept pixel in the beam at all (unknown; nothing is cleared there), ``right %``
the rest. Beams pooled per data set.

KITTI 2015 has no calibration in the shared data: its usual rectified values (fx 721.5 px at
1242 columns, baseline 0.54 m) are used. Middlebury 2003 has none either: fx = image width,
baseline 0.16 m. The band is set per scene from the median depth, so the scale of a guessed
baseline cancels; the scores are in disparity and do not depend on it.

Also the time of ``disparity_to_scan`` on a 640×480 map and ``scan_example.png`` (a top view of
one scene's scans).

    python docs/measurements/2026-11-24_scan/scan.py --data-root ../shared/data
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
import time

import numpy as np

from cva_confidence_ros.datasets import (
    DEVELOP_DATASETS,
    StereoSample,
    fit_disparity_range,
    list_scenes,
    load_scene,
)
from cva_confidence_ros.matching import remove_speckles
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.scan import Scan, ScanConfig, disparity_to_scan

MATCHERS = ('census_bm', 'census_sgm', 'mccnn_fast')
METHODS = ('all', 'speckle', 'node', 'node 0.8')
BANDS = ('centre', 'all heights')
OUTCOMES = ('right', 'phantom', 'far', 'none')
D = 64


def _geometry(sample: StereoSample) -> StereoGeometry:
    height, width = sample.left.shape[:2]
    if sample.calib is not None:
        c = sample.calib
        return StereoGeometry(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, cx_right=c.cx + c.doffs,
                              baseline=c.baseline)
    if sample.dataset == 'kitti2015':
        fx = 721.5377 * width / 1242
        return StereoGeometry(fx=fx, fy=fx, cx=609.5593 * width / 1242,
                              cy=172.854 * height / 375, cx_right=609.5593 * width / 1242,
                              baseline=0.5327)
    return StereoGeometry(fx=width, fy=width, cx=(width - 1) / 2, cy=(height - 1) / 2,
                          cx_right=(width - 1) / 2, baseline=0.16)


def _band(truth: np.ndarray, geometry: StereoGeometry, band: str) -> ScanConfig:
    if band == 'all heights':
        return ScanConfig(min_height=-1e6, max_height=1e6, range_min=0.0, range_max=1e6)
    depth = geometry.fx * geometry.baseline / (truth + geometry.disparity_offset)
    half = truth.shape[0] / 8 * float(np.nanmedian(depth)) / geometry.fy
    return ScanConfig(min_height=-half, max_height=half, range_min=0.0, range_max=1e6)


def _beam_disparity(scan: Scan, geometry: StereoGeometry) -> np.ndarray:
    """Each beam's range as a disparity (pitch 0: depth = range · cos(bearing))."""
    bearing = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)
    with np.errstate(divide='ignore', invalid='ignore'):
        depth = scan.ranges * np.cos(bearing)
        return geometry.fx * geometry.baseline / depth - geometry.disparity_offset


def _score(counts: dict[str, float], estimate: Scan, truth: Scan,
           geometry: StereoGeometry) -> None:
    d_est = _beam_disparity(estimate, geometry)
    d_gt = _beam_disparity(truth, geometry)
    scored = np.isfinite(truth.ranges)
    seen = np.isfinite(estimate.ranges)
    off = np.abs(d_est - d_gt)
    with np.errstate(invalid='ignore'):
        wrong = seen & (off >= 3.0) & (off >= 0.05 * d_gt)
        nearer = d_est > d_gt
    counts['beams'] += int(scored.sum())
    counts['none'] += int((scored & ~seen).sum())
    counts['phantom'] += int((scored & wrong & nearer).sum())
    counts['far'] += int((scored & wrong & ~nearer).sum())
    counts['right'] += int((scored & seen & ~wrong).sum())


def _masks(result, known: np.ndarray) -> dict[str, np.ndarray]:
    finite = np.isfinite(result.disparity)
    masks = {
        'all': finite,
        'speckle': remove_speckles(result.disparity, finite, 100, 1.0),
        'node': remove_speckles(result.disparity, finite & (result.confidence >= 0.5), 100, 1.0),
        'node 0.8': remove_speckles(result.disparity, finite & (result.confidence >= 0.8),
                                    100, 1.0),
    }
    return {name: mask & known for name, mask in masks.items()}


def _example_png(root: Path, out: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scene = list_scenes('kitti2015', root)[0]
    sample, _ = fit_disparity_range(load_scene('kitti2015', root, scene), D)
    geometry = _geometry(sample)
    pipeline = StereoPipeline(PipelineConfig(matcher='census_bm', speckle_size=0,
                                             confidence_threshold=0.0, device='cpu'))
    result = pipeline.process(sample.left, sample.right)
    known = np.isfinite(sample.disparity)
    config = _band(sample.disparity, geometry, 'centre')
    truth = disparity_to_scan(sample.disparity, geometry, known, None, config)
    masks = _masks(result, known)
    figure = Figure(figsize=(12.0, 6.4), dpi=90)
    FigureCanvasAgg(figure)
    for column, method in enumerate(('all', 'node')):
        scan = disparity_to_scan(result.disparity, geometry, masks[method], result.confidence,
                                 config)
        bearing = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.size)
        axes = figure.add_subplot(1, 2, column + 1)
        for ranges, style, label in ((truth.ranges, 'k.', 'ground truth'),
                                     (scan.ranges, 'r.', f'scan: {method}')):
            finite = np.isfinite(ranges)
            axes.plot(-ranges[finite] * np.sin(bearing[finite]),
                      ranges[finite] * np.cos(bearing[finite]), style, markersize=2,
                      label=label)
        counts: dict[str, float] = defaultdict(float)
        _score(counts, scan, truth, geometry)
        axes.set_title(f'KITTI 2015 {scene}, Census-BM, {method}: phantom '
                       f'{100 * counts["phantom"] / counts["beams"]:.1f} % of the beams, '
                       f'none {100 * counts["none"] / counts["beams"]:.1f} %', fontsize=9)
        axes.set_xlabel('right (m)')
        axes.set_ylabel('forward (m)')
        axes.set_aspect('equal')
        axes.set_xlim(-30, 30)
        axes.set_ylim(0, 60)
        axes.grid(True, alpha=0.3)
        axes.legend(fontsize=8, loc='upper left')
    figure.suptitle('Top view of a laser scan from stereo (centre band): every winner-takes-all '
                    'disparity vs the node (CVA-Net-Fast ≥ 0.5 + speckle filter)', fontsize=10)
    figure.tight_layout()
    figure.savefig(out, format='png')
    print(f'wrote {out}')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data-root', type=Path, required=True)
    args = parser.parse_args()
    counts: dict[tuple[str, str, str, str], dict[str, float]] = defaultdict(
        lambda: defaultdict(float))
    pipelines = {
        m: StereoPipeline(PipelineConfig(matcher=m, speckle_size=0, confidence_threshold=0.0,
                                         device='cpu'))
        for m in MATCHERS
    }
    for dataset in DEVELOP_DATASETS:
        for scene in list_scenes(dataset, args.data_root):
            sample, factor = fit_disparity_range(load_scene(dataset, args.data_root, scene), D)
            print(f'{dataset}/{scene}: {sample.left.shape[1]}×{sample.left.shape[0]} '
                  f'(1/{factor})', flush=True)
            geometry = _geometry(sample)
            known = np.isfinite(sample.disparity)
            configs = {band: _band(sample.disparity, geometry, band) for band in BANDS}
            truths = {band: disparity_to_scan(sample.disparity, geometry, known, None, config)
                      for band, config in configs.items()}
            for matcher in MATCHERS:
                result = pipelines[matcher].process(sample.left, sample.right)
                for method, mask in _masks(result, known).items():
                    for band, config in configs.items():
                        scan = disparity_to_scan(result.disparity, geometry, mask,
                                                 result.confidence, config)
                        _score(counts[dataset, matcher, band, method], scan, truths[band],
                               geometry)

    for band in BANDS:
        print(f'\nband: {band}; beams with a ground-truth return: phantom % / far % / none % '
              '(right % = the rest)\n')
        print('| data set | matcher | beams | ' + ' | '.join(METHODS) + ' |')
        print('|---|---|---:|' + '---|' * len(METHODS))
        for dataset in DEVELOP_DATASETS:
            for matcher in MATCHERS:
                cells = []
                for method in METHODS:
                    c = counts[dataset, matcher, band, method]
                    cells.append(' / '.join(f'{100 * c[o] / c["beams"]:.1f}'
                                            for o in ('phantom', 'far', 'none')))
                beams = int(counts[dataset, matcher, band, 'all']['beams'])
                print(f'| {dataset} | {matcher} | {beams} | ' + ' | '.join(cells) + ' |')

    # Cost at the size of a robot's camera: a real pair cut to 640×480.
    sample = load_scene('kitti2015', args.data_root, list_scenes('kitti2015', args.data_root)[0])
    left = np.concatenate([sample.left[:, :640], sample.left[:105, :640]])
    right = np.concatenate([sample.right[:, :640], sample.right[:105, :640]])
    pipeline = StereoPipeline(PipelineConfig(matcher='census_bm', max_disparity=128,
                                             device='cpu'))
    result = pipeline.process(left, right)
    geometry = StereoGeometry(fx=500.0, fy=500.0, cx=319.5, cy=239.5, cx_right=319.5,
                              baseline=0.12)
    config = ScanConfig(min_height=-0.5, max_height=0.5)
    disparity_to_scan(result.disparity, geometry, result.valid, result.confidence, config)
    times = []
    for _ in range(20):
        tic = time.perf_counter()
        disparity_to_scan(result.disparity, geometry, result.valid, result.confidence, config)
        times.append(time.perf_counter() - tic)
    print(f'\ndisparity_to_scan, 640×480 ({result.valid.mean():.0%} kept): '
          f'{1e3 * np.median(times):.2f} ms (median of 20)')
    _example_png(args.data_root, Path(__file__).parent / 'scan_example.png')


if __name__ == '__main__':
    main()
