"""One-off: what does the speckle filter add to the confidence threshold?

For each scene of the develop split (KITTI 2015, Middlebury 2003, Middlebury 2014 trainingQ
Motorcycle and MotorcycleE; halved until the ground truth fits D = 64, as ``cva-evaluate``
does) and each matcher, the node's pipeline runs with its defaults (CVA-Net-Fast, threshold
0.5, equiangular sub-pixel disparity) and without the speckle filter. On the kept pixels
(finite disparity, confidence ≥ 0.5) ``matching.remove_speckles`` then runs with each
``speckle_size`` × ``speckle_range``. Against the ground truth, per pixel with ground truth,
pooled over the scenes of a data set:

* ``kept %``: share of the ground-truth pixels kept; ``err %``: KITTI error rate of the kept
  pixels (|d − d_gt| ≥ 3 px and ≥ 5 %);
* ``thr err %``: the error rate when, instead of the speckle filter, the threshold is raised
  until as many pixels are kept in each scene (the most confident ones): the confidence alone
  at the same density. The filter adds something where ``err`` is below ``thr err``;
* ``pre err %``: stereo_image_proc's order, the filter on every finite disparity first and the
  threshold after (size 100 and 400 only), at its own density.

Also: the time of ``remove_speckles`` on a 640×480 map of a real pair (median of 20), and two
PNGs: ``speckle_tradeoff.png`` (error of the kept pixels against their share, the threshold
swept from 0.05 to 0.99, with the filter's points at threshold 0.5) and ``speckle_example.png``
(Middlebury 2014 Motorcycle, Census-BM: what the filter drops).

    python docs/measurements/2026-11-23_speckle/speckle.py --data-root ../shared/data
    python docs/measurements/2026-11-23_speckle/speckle.py --data-root ../shared/data \
        --downsample 2   # the tables at the node's downsample 2 (results_downsample2.txt)
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
    resize_disparity,
)
from cva_confidence_ros.matching import (
    compute_cost_volume,
    refine_subpixel,
    remove_speckles,
    wta_disparity,
)
from cva_confidence_ros.metrics import kitti_error
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

MATCHERS = ('census_bm', 'census_sgm', 'mccnn_fast')
SIZES = (25, 50, 100, 200, 400)
RANGES = (0.5, 1.0, 2.0, 4.0)
PRE_SIZES = (100, 400)
SWEEP = np.concatenate([np.linspace(0.05, 0.9, 18), np.linspace(0.92, 0.99, 8)])
D = 64
THRESHOLD = 0.5


def _most_confident(confidence: np.ndarray, kept: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` most confident pixels of ``kept``."""
    order = np.argsort(-np.where(kept, confidence, -1.0).ravel(), kind='stable')[:count]
    mask = np.zeros(confidence.size, bool)
    mask[order] = True
    return mask.reshape(confidence.shape)


def _score(totals: dict[str, float], key: str, mask: np.ndarray, known: np.ndarray,
           wrong: np.ndarray) -> None:
    totals[f'{key}/kept'] += int((mask & known).sum())
    totals[f'{key}/wrong'] += int((mask & known & wrong).sum())


def _rate(totals: dict[str, float], key: str) -> float:
    return 100 * totals[f'{key}/wrong'] / max(totals[f'{key}/kept'], 1)


def _share(totals: dict[str, float], key: str) -> float:
    return 100 * totals[f'{key}/kept'] / totals['n']


def _tradeoff_png(totals: dict, out: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(12.0, 10.0), dpi=100)
    FigureCanvasAgg(figure)
    for row, dataset in enumerate(DEVELOP_DATASETS):
        for column, matcher in enumerate(MATCHERS):
            t = totals[dataset, matcher]
            axes = figure.add_subplot(3, 3, 3 * row + column + 1)
            shares = [_share(t, f'sweep{tau:.3f}') for tau in SWEEP]
            rates = [_rate(t, f'sweep{tau:.3f}') for tau in SWEEP]
            axes.plot(shares, rates, 'k.-', linewidth=1, markersize=3,
                      label='threshold 0.05 … 0.99')
            axes.plot([_share(t, 'base')], [_rate(t, 'base')], 'ko', markersize=6,
                      label=f'threshold {THRESHOLD}')
            colours = ('tab:orange', 'tab:blue', 'tab:green', 'tab:red')
            for rng, colour in zip(RANGES, colours, strict=True):
                axes.plot([_share(t, f's{s}_r{rng}') for s in SIZES],
                          [_rate(t, f's{s}_r{rng}') for s in SIZES], 'o-', color=colour,
                          markersize=3, linewidth=1,
                          label=f'+ speckle 25 … 400 px, range {rng:g}')
            base = _share(t, 'base')
            axes.set_xlim(base - 12, base + 1)
            low = min(_rate(t, f's{s}_r{r}') for s in SIZES for r in RANGES)
            axes.set_ylim(low * 0.8, _rate(t, 'base') * 1.15)
            axes.set_title(f'{dataset}, {matcher}', fontsize=9)
            axes.set_xlabel('kept pixels (% of ground truth)', fontsize=8)
            axes.set_ylabel('error of the kept pixels %', fontsize=8)
            axes.tick_params(labelsize=7)
            axes.grid(True, alpha=0.3)
            if row == 0 and column == 0:
                axes.legend(fontsize=6)
    figure.suptitle('CVA-Net-Fast, D = 64: threshold alone vs threshold 0.5 + speckle filter '
                    '(lower right is better)', fontsize=10)
    figure.tight_layout()
    figure.savefig(out, format='png')
    print(f'wrote {out}')


def _example_png(root: Path, out: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    sample, _ = fit_disparity_range(load_scene('middlebury2014', root, 'Motorcycle'), D)
    pipeline = StereoPipeline(PipelineConfig(matcher='census_bm', speckle_size=0, device='cpu'))
    result = pipeline.process(sample.left, sample.right)
    kept = remove_speckles(result.disparity, result.valid, 100, 1.0)
    dropped = result.valid & ~kept
    known = np.isfinite(sample.disparity)
    wrong = kitti_error(result.disparity, sample.disparity)
    grey = result.left if result.left.ndim == 2 else result.left.mean(axis=2)
    picture = np.repeat((0.35 * grey / 255.0)[..., None], 3, axis=2)
    picture[result.valid & ~dropped] += np.array([0.0, 0.25, 0.0])
    picture[dropped & known & wrong] = (1.0, 0.1, 0.1)
    picture[dropped & known & ~wrong] = (0.2, 0.5, 1.0)
    picture[dropped & ~known] = (1.0, 0.9, 0.2)
    figure = Figure(figsize=(9.0, 6.6), dpi=90)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    axes.imshow(np.clip(picture, 0, 1))
    axes.set_axis_off()
    n_dropped = int((dropped & known).sum())
    share = 100 * (dropped & known & wrong).sum() / max(n_dropped, 1)
    before = 100 * (result.valid & known & wrong).sum() / (result.valid & known).sum()
    after = 100 * (kept & known & wrong).sum() / (kept & known).sum()
    axes.set_title(
        f'Motorcycle, Census-BM, CVA-Net-Fast ≥ 0.5 (green) + speckle 100 px / 1 px: dropped '
        f'wrong (red), right (blue), no ground truth (yellow)\n{share:.0f} % of the dropped '
        f'pixels with ground truth are wrong; error of the kept pixels {before:.2f} → '
        f'{after:.2f} %', fontsize=8)
    figure.tight_layout()
    figure.savefig(out, format='png')
    print(f'wrote {out}')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data-root', type=Path, required=True)
    parser.add_argument('--downsample', type=int, default=1, choices=(1, 2),
                        help="the node's downsample (2: the tables only, at half size)")
    args = parser.parse_args()
    totals: dict[tuple[str, str], dict[str, float]] = defaultdict(lambda: defaultdict(float))
    pipelines = {
        m: StereoPipeline(PipelineConfig(matcher=m, speckle_size=0, confidence_threshold=0.0,
                                         downsample=args.downsample, device='cpu'))
        for m in MATCHERS
    }
    for dataset in DEVELOP_DATASETS:
        for scene in list_scenes(dataset, args.data_root):
            sample, factor = fit_disparity_range(load_scene(dataset, args.data_root, scene), D)
            print(f'{dataset}/{scene}: {sample.left.shape[1]}×{sample.left.shape[0]} '
                  f'(1/{factor})', flush=True)
            truth = sample.disparity
            if args.downsample > 1:
                truth = resize_disparity(truth, args.downsample)
            known = np.isfinite(truth)
            for matcher in MATCHERS:
                t = totals[dataset, matcher]
                result = pipelines[matcher].process(sample.left, sample.right)
                disparity, confidence = result.disparity, result.confidence
                finite = np.isfinite(disparity)
                wrong = kitti_error(disparity, truth)
                base = finite & (confidence >= THRESHOLD)
                t['n'] += int(known.sum())
                _score(t, 'base', base, known, wrong)
                for tau in SWEEP:
                    _score(t, f'sweep{tau:.3f}', finite & (confidence >= tau), known, wrong)
                for size in SIZES:
                    for rng in RANGES:
                        kept = remove_speckles(disparity, base, size, rng)
                        _score(t, f's{size}_r{rng}', kept, known, wrong)
                        matched = _most_confident(confidence, base, int(kept.sum()))
                        _score(t, f'm{size}_r{rng}', matched, known, wrong)
                        if size in PRE_SIZES:
                            pre = remove_speckles(disparity, finite, size, rng) & base
                            _score(t, f'p{size}_r{rng}', pre, known, wrong)

    print('\nthreshold 0.5 + speckle filter on the kept pixels: kept % / err % (thr err %: the '
          'threshold raised to the same density)\n')
    header = ' | '.join(f'range {r:g}: kept % / err % / thr err %' for r in RANGES)
    print(f'| data set | matcher | size | {header} |')
    print('|---|---|---:|' + '---|' * len(RANGES))
    for (dataset, matcher), t in totals.items():
        print(f"| {dataset} | {matcher} | 0 | {_share(t, 'base'):.1f} / {_rate(t, 'base'):.2f}"
              + ' |' * len(RANGES))
        for size in SIZES:
            cells = ' | '.join(
                f"{_share(t, f's{size}_r{r}'):.1f} / {_rate(t, f's{size}_r{r}'):.2f} / "
                f"{_rate(t, f'm{size}_r{r}'):.2f}" for r in RANGES)
            print(f'| {dataset} | {matcher} | {size} | {cells} |')
    print('\nstereo_image_proc order (filter every finite disparity, then the threshold): '
          'kept % / err %\n')
    print('| data set | matcher | size | ' + ' | '.join(f'range {r:g}' for r in RANGES) + ' |')
    print('|---|---|---:|' + '---|' * len(RANGES))
    for (dataset, matcher), t in totals.items():
        for size in PRE_SIZES:
            cells = ' | '.join(
                f"{_share(t, f'p{size}_r{r}'):.1f} / {_rate(t, f'p{size}_r{r}'):.2f}"
                for r in RANGES)
            print(f'| {dataset} | {matcher} | {size} | {cells} |')

    if args.downsample > 1:
        return
    # Cost at the size of a robot's camera: a real pair cut to 640×480, D = 128.
    sample = load_scene('kitti2015', args.data_root, list_scenes('kitti2015', args.data_root)[0])
    left, right = sample.left[:, :640], sample.right[:, :640]
    left = np.concatenate([left, left[: 480 - left.shape[0]]])[:480]
    right = np.concatenate([right, right[: 480 - right.shape[0]]])[:480]
    volume = compute_cost_volume(left, right, 'census_bm', 128)
    disparity = refine_subpixel(volume, wta_disparity(volume))
    keep = np.isfinite(disparity)
    remove_speckles(disparity, keep)
    times = []
    for _ in range(20):
        tic = time.perf_counter()
        remove_speckles(disparity, keep, 100, 1.0)
        times.append(time.perf_counter() - tic)
    print(f'\nremove_speckles, 640×480, size 100, range 1: {1e3 * np.median(times):.2f} ms '
          '(median of 20)')
    here = Path(__file__).parent
    _tradeoff_png(totals, here / 'speckle_tradeoff.png')
    _example_png(args.data_root, here / 'speckle_example.png')


if __name__ == '__main__':
    main()
