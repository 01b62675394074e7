"""One-off: does CVA-Net's output order leave AUC on the table on Middlebury v3 (D = 256)?

Runs the shipped weights in patch mode on a fixed subset of ground-truth pixels of each scene
(the evaluator's ``select_pixels`` with seed 0), keeps the 16 pre-activations of the first
fully-connected layer, and scores:

* the float32 output as the evaluator scores it (ties handled by the interval extension);
* the float64 output (sigmoid saturates to exactly 1.0 in float32 for the surest pixels);
* the classification read with a leaky ReLU or a softplus instead of the ReLU (a soft readout
  that also orders pixels whose hidden units are off).

    python docs/measurements/2026-11-23_d256_ties/ties.py --data-root ../shared/data \
        --matcher census_bm --pixels 2000
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
import torch
import torch.nn.functional as F

from cva_confidence_ros.datasets import fit_disparity_range
from cva_confidence_ros.datasets.loaders import list_scenes, load_scene
from cva_confidence_ros.evaluation.scene import score_confidence, select_pixels
from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
from cva_confidence_ros.metrics import kitti_error, roc_auc
from cva_confidence_ros.model.inference import fold_batchnorm, pad_cost_volume
from cva_confidence_ros.model.network import DEPTH_KERNELS
from cva_confidence_ros.model.weights import default_weights_path, load_weights


def hidden_preactivations(fnet, volume, ys, xs, batch=256):
    """(N, 16) float64 pre-ReLU values of the first fully-connected layer at the pixels."""
    windows = sliding_window_view(pad_cost_volume(volume), (13, 13), axis=(1, 2))
    out = []
    with torch.inference_mode():
        for start in range(0, len(ys), batch):
            part = windows[:, ys[start:start + batch], xs[start:start + batch]].swapaxes(0, 1)
            x = fnet.fusion_features(torch.from_numpy(np.ascontiguousarray(part))[:, None])
            x = x[..., 0, 0]
            for conv, k in zip(fnet.depth, DEPTH_KERNELS, strict=True):
                x = F.relu(conv(F.pad(x, ((k - 1) // 2, k // 2))))
            out.append(fnet.fc1(x)[..., 0].numpy())
    return np.concatenate(out).astype(np.float64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data-root', required=True)
    parser.add_argument('--dataset', default='middlebury2014')
    parser.add_argument('--matcher', default='census_bm')
    parser.add_argument('--max-disparity', type=int, default=256)
    parser.add_argument('--pixels', type=int, default=2000)
    args = parser.parse_args()
    torch.set_num_threads(2)
    net, _ = load_weights(default_weights_path(args.matcher, args.max_disparity),
                          args.matcher, args.max_disparity)
    fnet = fold_batchnorm(net)
    w = fnet.fc2.weight.reshape(-1).double().numpy()
    b = float(fnet.fc2.bias)
    print(f'fc2 weights: {np.sum(w > 0)} positive, {np.sum(w < 0)} negative; bias {b:.3f}')
    for scene in list_scenes(args.dataset, args.data_root):
        sample, _ = fit_disparity_range(load_scene(args.dataset, args.data_root, scene),
                                        args.max_disparity)
        gt = np.asarray(sample.disparity, np.float32)
        ys, xs = select_pixels(np.isfinite(gt), args.pixels, 0)
        volume = compute_cost_volume(sample.left, sample.right, args.matcher, args.max_disparity)
        error = np.asarray(kitti_error(wta_disparity(volume), gt), bool)[ys, xs]
        tic = time.perf_counter()
        z = hidden_preactivations(fnet, volume, ys, xs)
        logit = b + np.maximum(z, 0) @ w
        conf64 = 1 / (1 + np.exp(-logit))
        conf32 = conf64.astype(np.float32)
        values, counts = np.unique(conf32, return_counts=True)
        top = counts.argmax()
        scored = score_confidence(conf32, error)
        print(f'{scene}: {len(ys)} px, {time.perf_counter() - tic:.0f} s, error rate '
              f'{error.mean():.3f}; AUC x100 {100 * scored.auc:.3f} '
              f'(opt {100 * scored.auc_opt:.3f})')
        print(f'  largest float32 tie: {counts[top] / len(ys):.3f} of the pixels at '
              f'{values[top]:.6f}; all 16 hidden units off: {np.mean((z <= 0).all(1)):.3f}')
        print(f'  float64 output (no ties): {100 * roc_auc(conf64, error):.3f}')
        for slope in (1e-3, 1e-2, 0.1, 0.3):
            leaky = b + np.where(z > 0, z, slope * z) @ w
            print(f'  leaky ReLU {slope}: {100 * roc_auc(leaky, error):.3f}')
        for temperature in (0.1, 0.3, 1.0):
            soft = b + (temperature * np.logaddexp(0, z / temperature)) @ w
            print(f'  softplus T = {temperature}: {100 * roc_auc(soft, error):.3f}')


if __name__ == '__main__':
    main()
