"""One-off: what the region of interest (``roi_top``, ``roi_bottom``) saves, and what it changes.

The node's pipeline (``StereoPipeline``: CVA-Net-Fast, equiangular sub-pixel disparity, speckle
filter, D = 128, CPU, 2 threads) on the Motorcycle pair of scikit-image resized to 640×480, for
Census-BM and Census-SGM and four regions: the whole image, the lower 60 % (``roi_top`` 0.4:
no sky or ceiling), 0.25–0.85 (neither the top quarter nor a hood in the bottom 15 %) and the
lower half. Per row: the median time of ``--repeat`` frames (after one untimed frame; the
configurations interleaved frame by frame, so that a slower spell of the machine hits all of
them alike), its ratio to the whole image, the share of rows processed (region plus the
16-row margin of context above and below), and how many disparities and confidences inside
the region equal the whole-image ones (and the mean absolute change of the confidence).

    python docs/measurements/2026-11-24_roi/roi.py [--repeat 7]
    python docs/measurements/2026-11-24_roi/roi.py --exactness

``--exactness`` instead compares integer disparities (``subpixel`` none) and confidences
inside the region with the whole image's for MC-CNN and Census-SGM (no timing): MC-CNN
standardises each image by its own mean and deviation, so a region's features shift a little.
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2
import numpy as np
from skimage import data
import torch

from cva_confidence_ros.pipeline import ROI_MARGIN, PipelineConfig, StereoPipeline

REGIONS = ((0.0, 1.0), (0.4, 1.0), (0.25, 0.85), (0.5, 1.0))
MATCHERS = ('census_bm', 'census_sgm')


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=7)
    parser.add_argument('--exactness', action='store_true')
    args = parser.parse_args()
    torch.set_num_threads(2)
    left, right, _ = data.stereo_motorcycle()
    left = cv2.resize(left, (640, 480), interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, (640, 480), interpolation=cv2.INTER_AREA)
    if args.exactness:
        _exactness(left, right)
        return
    pipelines = {
        (matcher, region): StereoPipeline(PipelineConfig(
            matcher=matcher, max_disparity=128, device='cpu', roi_top=region[0],
            roi_bottom=region[1]))
        for matcher in MATCHERS for region in REGIONS
    }
    results = {key: pipeline.process(left, right) for key, pipeline in pipelines.items()}
    times: dict[tuple[str, tuple[float, float]], list[float]] = {key: [] for key in pipelines}
    for frame in range(args.repeat):
        for key, pipeline in pipelines.items():
            tic = time.perf_counter()
            pipeline.process(left, right)
            times[key].append((time.perf_counter() - tic) * 1e3)
        print(f'frame {frame + 1}/{args.repeat}', flush=True)
    print('\n| matcher | region | rows processed % | ms (median) | × whole | equal disparities % '
          '| equal confidences % | mean abs. confidence change |')
    print('|---|---|---:|---:|---:|---:|---:|---:|')
    for matcher in MATCHERS:
        whole = statistics.median(times[matcher, REGIONS[0]])
        reference = results[matcher, REGIONS[0]]
        for region in REGIONS:
            result = results[matcher, region]
            y0, y1 = result.rows
            processed = min(480, y1 + ROI_MARGIN) - max(0, y0 - ROI_MARGIN)
            a, b = result.disparity[y0:y1], reference.disparity[y0:y1]
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            change = np.abs(result.confidence[y0:y1] - reference.confidence[y0:y1])
            median = statistics.median(times[matcher, region])
            print(f'| {matcher} | {region[0]:g}–{region[1]:g} | {100 * processed / 480:.0f} '
                  f'| {median:.0f} | {median / whole:.2f} | {100 * same.mean():.2f} '
                  f'| {100 * (change == 0).mean():.2f} | {change.mean():.4f} |')


def _exactness(left: np.ndarray, right: np.ndarray) -> None:
    print('| matcher | region | equal integer disparities % | mean abs. confidence change |')
    print('|---|---|---:|---:|')
    for matcher in ('mccnn_fast', 'census_sgm'):
        base = {'matcher': matcher, 'max_disparity': 128, 'device': 'cpu', 'speckle_size': 0,
                'subpixel': 'none'}
        whole = StereoPipeline(PipelineConfig(**base)).process(left, right)
        for top, bottom in REGIONS[1:]:
            part = StereoPipeline(PipelineConfig(**base, roi_top=top, roi_bottom=bottom)).process(
                left, right)
            y0, y1 = part.rows
            a, b = part.disparity[y0:y1], whole.disparity[y0:y1]
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            change = np.abs(part.confidence[y0:y1] - whole.confidence[y0:y1]).mean()
            print(f'| {matcher} | {top:g}–{bottom:g} | {100 * same.mean():.2f} | {change:.4f} |',
                  flush=True)


if __name__ == '__main__':
    main()
