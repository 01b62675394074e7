"""One-off: how much does the sub-pixel curve improve the published disparity and depth?

For each scene of the develop split (KITTI 2015, Middlebury 2003, Middlebury 2014 trainingQ
Motorcycle and MotorcycleE; halved until the ground truth fits D = 64, as ``cva-evaluate``
does) and each matcher, the node's pipeline (``StereoPipeline``, CVA-Net-Fast, threshold 0.5)
runs with ``subpixel`` none, parabola and equiangular. Against the ground truth, per pixel with
ground truth (pooled over the scenes of a data set):

* ``error %``: KITTI criterion (|d − d_gt| ≥ 3 px and ≥ 5 %);
* ``EPE``: mean |d − d_gt| in pixels at the processed resolution, over all pixels with ground
  truth; ``EPE ok``: the same over the pixels that are right by the KITTI criterion for the
  integer disparity (the precision of the inliers, what the curve is for);
* ``< 0.5 px %``: share within half a pixel;
* ``kept EPE`` / ``kept depth err %``: over the pixels the node keeps (finite disparity,
  confidence ≥ 0.5), the mean |d − d_gt| and the mean relative depth error |Z − Z_gt| / Z_gt =
  |d_gt / d − 1| (pixels with d > 0), what a mapper gets from ``depth`` and ``points2``.

Also: the time of ``refine_subpixel`` on a 640×480, D = 128 volume of a real pair (median of
20), and ``subpixel_profile.png``, a row of the Motorcycle pair (Census-SGM) with the ground
truth, the integer and the equiangular disparity, and the histograms of d − d_gt of the right
pixels.

    python docs/measurements/2026-11-23_subpixel/subpixel.py --data-root ../shared/data
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
import time

import numpy as np

from cva_confidence_ros.datasets import (
    DEVELOP_DATASETS,
    fit_disparity_range,
    list_scenes,
    load_scene,
)
from cva_confidence_ros.matching import compute_cost_volume, refine_subpixel, wta_disparity
from cva_confidence_ros.metrics import kitti_error
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

MATCHERS = ('census_bm', 'census_sgm', 'mccnn_fast')
METHODS = ('none', 'parabola', 'equiangular')
D = 64


def _stats(disparity: np.ndarray, truth: np.ndarray, right: np.ndarray, kept: np.ndarray):
    known = np.isfinite(truth)
    dev = np.abs(disparity - truth)
    wrong = kitti_error(disparity, truth)
    depth_mask = kept & known & (disparity > 0)
    return {
        'n': int(known.sum()),
        'wrong': int(wrong[known].sum()),
        'dev': float(dev[known].sum()),
        'dev_ok': float(dev[known & right].sum()),
        'n_ok': int((known & right).sum()),
        'half': int((dev[known] < 0.5).sum()),
        'kept_dev': float(dev[kept & known].sum()),
        'n_kept': int((kept & known).sum()),
        'depth': float(np.abs(truth[depth_mask] / disparity[depth_mask] - 1).sum()),
        'n_depth': int(depth_mask.sum()),
    }


_SEGMENT = 80


def _slanted_segment(truth: np.ndarray, integer: np.ndarray) -> tuple[int, int]:
    """(row, first column) of the steepest smooth run of ground truth (no step above 0.3 px
    between neighbours) where the integer disparity is within 1 px everywhere: a slanted
    surface, where integer disparities make a staircase."""
    best, where = -1.0, (0, 0)
    for row in range(0, truth.shape[0], 4):
        line, found = truth[row], integer[row]
        for start in range(0, truth.shape[1] - _SEGMENT, 8):
            gt = line[start : start + _SEGMENT]
            if not np.all(np.isfinite(gt)) or np.max(np.abs(np.diff(gt))) > 0.3:
                continue
            if np.max(np.abs(found[start : start + _SEGMENT] - gt)) > 1.0:
                continue
            if np.ptp(gt) > best:
                best, where = float(np.ptp(gt)), (row, start)
    return where


def _profile(root: Path, out: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    sample, _ = fit_disparity_range(load_scene('middlebury2014', root, 'Motorcycle'), D)
    volume = compute_cost_volume(sample.left, sample.right, 'census_sgm', D)
    integer = wta_disparity(volume)
    refined = refine_subpixel(volume, integer, 'equiangular')
    truth = sample.disparity
    row, start = _slanted_segment(truth, integer)
    columns = np.arange(start, start + _SEGMENT)
    figure = Figure(figsize=(10.0, 3.6), dpi=110)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 2, 1)
    axes.plot(columns, truth[row, columns], 'k-', linewidth=1.5, label='ground truth')
    axes.step(columns, integer[row, columns], where='mid', color='tab:red', linewidth=1,
              label='winner-takes-all (integer)')
    axes.plot(columns, refined[row, columns], '.', color='tab:blue', markersize=3,
              label='equiangular sub-pixel')
    axes.set_xlabel(f'column (row {row})')
    axes.set_ylabel('disparity (px)')
    axes.set_title('Motorcycle, Census-SGM, D = 64')
    axes.legend(fontsize=7)
    axes.grid(True, alpha=0.3)
    axes = figure.add_subplot(1, 2, 2)
    known = np.isfinite(truth)
    right = known & ~kitti_error(integer, truth) & (np.abs(integer - truth) < 1.5)
    bins = np.linspace(-1.5, 1.5, 61)
    axes.hist((integer - truth)[right], bins, histtype='step', color='tab:red',
              label='winner-takes-all')
    axes.hist((refined - truth)[right], bins, histtype='step', color='tab:blue',
              label='equiangular')
    axes.set_xlabel('d − d_gt (px), pixels within 1.5 px')
    axes.set_ylabel('pixels')
    axes.legend(fontsize=7)
    axes.grid(True, alpha=0.3)
    figure.tight_layout()
    figure.savefig(out, format='png')
    print(f'wrote {out}')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data-root', type=Path, required=True)
    args = parser.parse_args()
    totals: dict[tuple[str, str, str], dict[str, float]] = defaultdict(lambda: defaultdict(float))
    pipelines = {
        (m, s): StereoPipeline(PipelineConfig(matcher=m, subpixel=s, device='cpu'))
        for m in MATCHERS for s in METHODS
    }
    for dataset in DEVELOP_DATASETS:
        for scene in list_scenes(dataset, args.data_root):
            sample, factor = fit_disparity_range(load_scene(dataset, args.data_root, scene), D)
            print(f'{dataset}/{scene}: {sample.left.shape[1]}×{sample.left.shape[0]} '
                  f'(1/{factor})', flush=True)
            truth = sample.disparity
            for matcher in MATCHERS:
                results = {s: pipelines[matcher, s].process(sample.left, sample.right)
                           for s in METHODS}
                integer = results['none'].disparity
                right = ~kitti_error(integer, truth)
                for method, result in results.items():
                    for key, value in _stats(result.disparity, truth, right,
                                             result.valid).items():
                        totals[dataset, matcher, method][key] += value
    print()
    print('| data set | matcher | subpixel | error % | EPE px | EPE ok px | < 0.5 px % '
          '| kept EPE px | kept depth err % |')
    print('|---|---|---|---:|---:|---:|---:|---:|---:|')
    for (dataset, matcher, method), t in totals.items():
        print(f"| {dataset} | {matcher} | {method} | {100 * t['wrong'] / t['n']:.2f} "
              f"| {t['dev'] / t['n']:.3f} | {t['dev_ok'] / t['n_ok']:.3f} "
              f"| {100 * t['half'] / t['n']:.1f} | {t['kept_dev'] / t['n_kept']:.3f} "
              f"| {100 * t['depth'] / t['n_depth']:.2f} |", flush=True)

    # Cost at the size of a robot's camera: a real pair cut to 640×480, D = 128.
    sample = load_scene('kitti2015', args.data_root, list_scenes('kitti2015', args.data_root)[0])
    left, right = sample.left[:, :640], sample.right[:, :640]
    left = np.concatenate([left, left[: 480 - left.shape[0]]])[:480]
    right = np.concatenate([right, right[: 480 - right.shape[0]]])[:480]
    volume = compute_cost_volume(left, right, 'census_bm', 128)
    integer = wta_disparity(volume)
    for method in ('parabola', 'equiangular'):
        refine_subpixel(volume, integer, method)
        times = []
        for _ in range(20):
            tic = time.perf_counter()
            refine_subpixel(volume, integer, method)
            times.append(time.perf_counter() - tic)
        wta = []
        for _ in range(5):
            tic = time.perf_counter()
            wta_disparity(volume)
            wta.append(time.perf_counter() - tic)
        print(f'refine_subpixel {method}, 640×480, D = 128: {1e3 * np.median(times):.2f} ms '
              f'(wta_disparity on the same volume: {1e3 * np.median(wta):.1f} ms)')
    _profile(args.data_root, Path(__file__).with_name('subpixel_profile.png'))


if __name__ == '__main__':
    main()
