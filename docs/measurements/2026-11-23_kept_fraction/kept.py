"""One-off: does the node's ``kept_fraction`` (share of confident pixels) show a degraded camera?

Runs the node's pipeline (default matcher and method: Census-BM, CVA-Net-Fast, D = 64,
threshold 0.5) on the scikit-image Motorcycle pair at half size (370×248 after the pipeline's
crop) and on degraded copies of it, and prints the share of pixels kept (finite disparity,
confidence ≥ threshold; what ``/diagnostics`` reports), the error rate the confidence
predicts for them (``expected_kept_error``, mean(1 − confidence); also in ``/diagnostics``)
and, against the pair's ground truth, their measured error rate (KITTI criterion, ground truth
at the processed size):

* ``rows off by k px``: the right image shifted down by k rows (a rectification gone wrong);
* ``blur σ``: both images Gaussian-blurred (fog, condensation, defocus);
* ``dark ×g + noise``: both images times g plus Gaussian noise of σ 2 grey levels (night);
* ``left half covered``: the left half of the left image black (a hand, a leaf, mud);
* ``right lens covered``: the right image uniform grey.

    python docs/measurements/2026-11-23_kept_fraction/kept.py
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from skimage import data

from cva_confidence_ros.datasets import resize_disparity
from cva_confidence_ros.metrics import kitti_error
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline


def main() -> None:
    left, right, gt = data.stereo_motorcycle()
    rng = np.random.default_rng(0)
    pipeline = StereoPipeline(PipelineConfig(downsample=2))
    pipeline.warm_up()

    def shifted(image: np.ndarray, rows: int) -> np.ndarray:
        out = np.roll(image, rows, axis=0)
        out[:rows] = image[:1]
        return out

    def dark(image: np.ndarray, gain: float) -> np.ndarray:
        noisy = image.astype(np.float64) * gain + rng.normal(0.0, 2.0, image.shape)
        return np.clip(noisy, 0, 255).astype(np.uint8)

    def covered(image: np.ndarray) -> np.ndarray:
        out = image.copy()
        out[:, : image.shape[1] // 2] = 0
        return out

    cases = [('original', left, right)]
    for rows in (1, 2, 4):
        cases.append((f'rows off by {rows} px', left, shifted(right, rows)))
    for sigma in (2.0, 4.0):
        cases.append((f'blur σ {sigma:g}', cv2.GaussianBlur(left, (0, 0), sigma),
                      cv2.GaussianBlur(right, (0, 0), sigma)))
    for gain in (0.1, 0.03):
        cases.append((f'dark ×{gain:g} + noise', dark(left, gain), dark(right, gain)))
    cases.append(('left half covered', covered(left), right))
    cases.append(('right lens covered', left, np.full_like(right, 128)))

    print('| input | kept fraction | mean confidence | predicted error % of the kept pixels '
          '| error % of the kept pixels | s |')
    print('|---|---:|---:|---:|---:|---:|')
    for name, a, b in cases:
        tic = time.perf_counter()
        result = pipeline.process(a, b)
        seconds = time.perf_counter() - tic
        height, width = result.disparity.shape
        truth = resize_disparity(np.asarray(gt, np.float32), 2)[:height, :width]
        known = np.isfinite(truth) & result.valid
        wrong = kitti_error(result.disparity[known], truth[known])
        error = f'{100 * wrong.mean():.1f}' if wrong.size else '– (none kept)'
        predicted = result.expected_kept_error
        guess = '–' if predicted is None else f'{100 * predicted:.1f}'
        print(
            f'| {name} | {result.valid.mean():.3f} | {np.nanmean(result.confidence):.3f} '
            f'| {guess} | {error} | {seconds:.1f} |',
            flush=True,
        )


if __name__ == '__main__':
    main()
