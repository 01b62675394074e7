"""One-off experiment: how to fill the pixels CVA-Net's sparse paths skip.

Scores fill rules of the strided path and cascades against the exact network's maps, on one
120×200 window (the one with the most ground truth of 9 candidates) of every scene of the train
split and of the develop split, D = 64, census_bm, the shipped GPU-trained CVA-Net and
CVA-Net-Fast weights. The exact maps are computed once per split and cached (``--cache``);
every rule then reads the network's values at the pixels it would have evaluated from them.

Rules: ``current`` (what ``sparse_confidence`` does), ``iso+G`` (a guide measure G on every
pixel, mapped onto the network's logit by an increasing map fitted on the grid pixels, plus the
joint-bilateral fill of the residual), ``lin+fast`` (the same with a straight-line map),
``,nores`` (the mapped guide alone), ``scX sdY`` (the fill's colour / disparity sigmas; 1e6 =
that term off), and cascades with PKRN or CVA-Net-Fast as the cheap measure.

    python docs/measurements/2026-11-23_sparse_fill/fill_experiment.py \\
        --data-root ../shared/data --split develop --cache out/fill_cache

Output: one line per rule, mean AUC over the windows and that over the exact network's.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.datasets import DEVELOP_DATASETS, TRAIN_DATASETS, list_scenes, load_scene
from cva_confidence_ros.datasets.resize import fit_disparity_range
from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
from cva_confidence_ros.metrics import kitti_error, roc_auc
from cva_confidence_ros.model import (
    SparseConfig,
    SparseEvaluator,
    default_weights_path,
    load_weights,
    sparse_confidence,
)
from cva_confidence_ros.model.sparse import (
    _grid_axis,
    _logit,
    _ranks,
    _sigmoid,
    joint_bilateral_fill,
    monotone_map,
)

DEPTH = 64
MATCHER = 'census_bm'
WINDOW = (120, 200)


def windows(root: Path, datasets: tuple[str, ...]) -> list[dict]:
    """One scored window per scene (at most 4 scenes per data set) with its cost volumes."""
    out = []
    for dataset in datasets:
        try:
            scenes = list_scenes(dataset, root)
        except Exception as error:  # noqa: BLE001 - a data set missing here is skipped
            print(f'skip {dataset}: {error}', file=sys.stderr)
            continue
        for scene in scenes[:4]:
            sample, _ = fit_disparity_range(load_scene(dataset, root, scene), DEPTH)
            known = np.isfinite(sample.disparity)
            height, width = known.shape
            rows, cols = min(WINDOW[0], height), min(WINDOW[1], width)
            best, corner = -1, (0, 0)
            for fy in (0.25, 0.5, 0.75):
                for fx in (0.25, 0.5, 0.75):
                    y0, x0 = int(fy * (height - rows)), int(fx * (width - cols))
                    count = int(known[y0:y0 + rows, x0:x0 + cols].sum())
                    if count > best:
                        best, corner = count, (y0, x0)
            box = (slice(corner[0], corner[0] + rows), slice(corner[1], corner[1] + cols))
            volume = compute_cost_volume(sample.left, sample.right, MATCHER, DEPTH)
            right = compute_cost_volume(sample.left, sample.right, MATCHER, DEPTH, view='right')
            disparity = wta_disparity(volume)
            truth = sample.disparity[box]
            out.append({
                'name': f'{dataset}/{scene}',
                'volume': np.ascontiguousarray(volume[:, box[0], box[1]]),
                'volume_right': np.ascontiguousarray(right[:, box[0], box[1]]),
                'disparity': np.ascontiguousarray(disparity[box]),
                'image': np.ascontiguousarray(sample.left[box]),
                'wrong': kitti_error(disparity[box], np.nan_to_num(truth)),
                'known': np.isfinite(truth),
            })
            print(f"{out[-1]['name']}: {best} known pixels", file=sys.stderr, flush=True)
    return out


def load_or_build(root: Path, split: str, cache: Path) -> list[dict]:
    path = cache / f'{split}_{MATCHER}_d{DEPTH}.npz'
    if path.exists():
        return list(np.load(path, allow_pickle=True)['items'])
    items = windows(root, DEVELOP_DATASETS if split == 'develop' else TRAIN_DATASETS)
    net, _ = load_weights(default_weights_path(MATCHER, DEPTH), MATCHER, DEPTH)
    fast, _ = load_weights(default_weights_path(MATCHER, DEPTH, 'cvanet_fast'), MATCHER, DEPTH,
                           arch='cvanet_fast')
    exact, light = SparseEvaluator(net), SparseEvaluator(fast)
    for item in items:
        tic = time.perf_counter()
        item['exact'] = exact(item['volume'])
        item['fast'] = light(item['volume'])
        print(f"{item['name']}: exact map {time.perf_counter() - tic:.0f} s",
              file=sys.stderr, flush=True)
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, items=np.array(items, dtype=object))
    return items


def guided(item: dict, stride: int, guide: np.ndarray | None, fit: str = 'iso',
           sigma_color: float = 12.0, sigma_disparity: float = 2.0,
           residual: bool = True) -> np.ndarray:
    """Strided network values plus a guide mapped onto its logit and a filled residual."""
    exact = item['exact']
    shape = exact.shape
    rows, cols = _grid_axis(shape[0], stride), _grid_axis(shape[1], stride)
    grid = np.zeros(shape, dtype=bool)
    grid[np.ix_(rows, cols)] = True
    target = _logit(exact)
    if guide is None:
        base = np.zeros(shape)
    elif fit == 'iso':
        rank = _ranks(guide)
        base = monotone_map(rank[grid], target[grid], rank)
    else:
        slope, intercept = np.polyfit(guide[grid], target[grid], 1)
        base = slope * guide.astype(np.float64) + intercept
    if residual:
        sub = np.ix_(rows, cols)
        filled = joint_bilateral_fill((target - base)[sub], grid[sub], stride, item['image'],
                                      item['disparity'], sigma_color, sigma_disparity)
        out = _sigmoid(base + filled)
    else:
        out = _sigmoid(base)
    out[grid] = exact[grid]
    return out


def cheap(name: str, item: dict) -> np.ndarray:
    inputs = ConfidenceInputs(item['volume'], item['disparity'], item['image'],
                              cost_volume_right=item['volume_right'])
    return CONFIDENCE_METHODS.get(name)()(inputs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data-root', type=Path, required=True)
    parser.add_argument('--split', choices=('train', 'develop'), default='develop')
    parser.add_argument('--cache', type=Path, default=Path('out/fill_cache'))
    args = parser.parse_args()
    items = load_or_build(args.data_root, args.split, args.cache)
    for item in items:
        for name in ('pkrn', 'score', 'mlm', 'lrd'):
            item[name] = cheap(name, item)
        item['fast_logit'] = _logit(item['fast'])
    aucs: dict[str, list[float]] = {}

    def score(name, rule):
        aucs[name] = [roc_auc(rule(it)[it['known']], it['wrong'][it['known']]) for it in items]

    score('exact', lambda it: it['exact'])
    score('cva_net_fast alone', lambda it: it['fast'])
    for name in ('pkrn', 'score', 'mlm', 'lrd'):
        score(f'{name} alone', lambda it, n=name: it[n])
    for s in (2, 4, 8):
        score(f'stride {s} current', lambda it, s=s: sparse_confidence(
            lambda _v, _m, it=it: it['exact'], it['volume'], it['image'], it['disparity'],
            SparseConfig(stride=s)).confidence)
        for sc, sd in ((6.0, 1.0), (24.0, 4.0), (48.0, 8.0), (12.0, 1e6), (1e6, 2.0),
                       (1e6, 1e6)):
            score(f'stride {s} no guide sc{sc:g} sd{sd:g}', lambda it, s=s, sc=sc, sd=sd:
                  guided(it, s, None, sigma_color=sc, sigma_disparity=sd))
        for name in ('pkrn', 'score', 'mlm', 'lrd'):
            score(f'stride {s} iso+{name}', lambda it, s=s, n=name: guided(it, s, it[n]))
        score(f'stride {s} iso+fast', lambda it, s=s: guided(it, s, it['fast_logit']))
        score(f'stride {s} lin+fast', lambda it, s=s: guided(it, s, it['fast_logit'], 'lin'))
        score(f'stride {s} iso+fast,nores', lambda it, s=s: guided(
            it, s, it['fast_logit'], residual=False))
        score(f'stride {s} iso+fast sc1e6 sd1e6', lambda it, s=s: guided(
            it, s, it['fast_logit'], sigma_color=1e6, sigma_disparity=1e6))
    for s in (1, 8):
        for name, key in (('pkrn', 'pkrn'), ('cva_net_fast', 'fast')):
            for fraction in (0.1, 0.25):
                score(f'stride {s} cascade {name} {fraction}',
                      lambda it, s=s, k=key, f=fraction: sparse_confidence(
                          lambda _v, _m, it=it: it['exact'], it['volume'], it['image'],
                          it['disparity'], SparseConfig(s, 'pkrn', f), it[k]).confidence)
    reference = float(np.mean(aucs['exact']))
    names = ', '.join(
        f"{it['name']} {a:.4f}" for it, a in zip(items, aucs['exact'], strict=True)
    )
    print(f'{len(items)} windows ({args.split}), exact AUC: {names}')
    print('| rule | mean AUC | / exact |\n|---|---:|---:|')
    for name, values in aucs.items():
        print(f'| {name} | {np.mean(values):.4f} | {np.mean(values) / reference:.3f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
