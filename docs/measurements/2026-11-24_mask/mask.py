"""One-off: what an ignore mask (``mask_path``) costs and saves, and what it changes.

The node's pipeline (``StereoPipeline``: Census-BM, CVA-Net-Fast, equiangular sub-pixel
disparity, speckle filter, D = 128, CPU, 2 threads) on the Motorcycle pair of scikit-image
resized to 640×480, with three masks drawn by ``cva-mask``'s ``draw_mask``:

* ``corners``: two bumper corners (triangles 160 px wide and 120 px high in the lower corners);
  no row is black from edge to edge, so every row is still processed;
* ``hood``: the corners and a hood over the lowest 72 rows (15 %), which are not processed;
* ``mast``: the hood, the corners and a mast (a 40 px wide column over the whole height).

Per mask: the median time of ``--repeat`` frames (after one untimed frame; the configurations
interleaved frame by frame), its ratio to no mask, the rows processed, the share of pixels
judged, whether the judged pixels hold exactly the values without a mask, and the time of the
masking itself (three ``np.where`` over the maps and the judged region; median of 50).

    python docs/measurements/2026-11-24_mask/mask.py [--repeat 7]
"""

from __future__ import annotations

import argparse
from pathlib import Path
import statistics
import tempfile
import time

import cv2
import numpy as np
from skimage import data
import torch

from cva_confidence_ros.pipeline import ROI_MARGIN, PipelineConfig, StereoPipeline, judged_region
from msg_tools.mask_tool import draw_mask

WIDTH, HEIGHT = 640, 480


def masks() -> dict[str, np.ndarray]:
    corners = [np.array([(0, 360), (160, 480), (0, 480)], np.int32),
               np.array([(640, 360), (480, 480), (640, 480)], np.int32)]
    hood = draw_mask(WIDTH, HEIGHT, polygons=corners, below=408)
    return {
        'corners': draw_mask(WIDTH, HEIGHT, polygons=corners),
        'hood': hood,
        'mast': draw_mask(WIDTH, HEIGHT, start=hood, rects=[[300, 0, 340, 480]]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeat', type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(2)
    left, right, _ = data.stereo_motorcycle()
    left = cv2.resize(left, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA)
    base = PipelineConfig(matcher='census_bm', max_disparity=128, device='cpu')
    folder = Path(tempfile.mkdtemp())
    pipelines = {'none': StereoPipeline(base)}
    for name, keep in masks().items():
        path = folder / f'{name}.png'
        cv2.imwrite(str(path), np.where(keep, 255, 0).astype(np.uint8))
        pipelines[name] = StereoPipeline(base.replace(mask_path=str(path)))
    results = {name: pipeline.process(left, right) for name, pipeline in pipelines.items()}
    times: dict[str, list[float]] = {name: [] for name in pipelines}
    for frame in range(args.repeat):
        for name, pipeline in pipelines.items():
            tic = time.perf_counter()
            pipeline.process(left, right)
            times[name].append((time.perf_counter() - tic) * 1e3)
        print(f'frame {frame + 1}/{args.repeat}', flush=True)
    reference = results['none']
    print('\n| mask | rows processed % | pixels judged % | ms (median) | × no mask '
          '| judged pixels equal % | masking ms |')
    print('|---|---:|---:|---:|---:|---:|---:|')
    whole = statistics.median(times['none'])
    for name, result in results.items():
        y0, y1 = result.rows
        processed = min(HEIGHT, y1 + ROI_MARGIN) - max(0, y0 - ROI_MARGIN)
        region = result.region
        judged = np.ones((HEIGHT, WIDTH), bool) if region is None else region
        same = all(
            np.array_equal(getattr(result, key)[judged], getattr(reference, key)[judged],
                           equal_nan=key != 'valid')
            for key in ('disparity', 'confidence', 'raw_confidence')
        )
        masking = _masking_ms(reference, result.mask) if result.mask is not None else 0.0
        median = statistics.median(times[name])
        print(f'| {name} | {100 * processed / HEIGHT:.0f} | {100 * judged.mean():.1f} '
              f'| {median:.0f} | {median / whole:.2f} | {100.0 if same else 0.0:.0f} '
              f'| {masking:.2f} |')


def _masking_ms(result, mask: np.ndarray) -> float:
    samples = []
    for _ in range(50):
        tic = time.perf_counter()
        for values, fill in ((result.disparity, np.nan), (result.confidence, 0.0),
                             (result.raw_confidence, np.nan)):
            np.where(mask, values, np.float32(fill)).astype(np.float32, copy=False)
        judged_region(mask.shape, (0, mask.shape[0]), mask)
        samples.append((time.perf_counter() - tic) * 1e3)
    return statistics.median(samples)


if __name__ == '__main__':
    main()
