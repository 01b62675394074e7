"""Review 37 of the hand-crafted measures and the learned baselines against their definitions.

The measures are checked against independent per-pixel numpy references of Hu & Mordohai's
definitions (TPAMI 2012) on tiny volumes (D = 8, 6×5 px), including ties of the two smallest
costs, perfect matches and right partners outside the image; the baselines' layer shapes,
parameter counts and receptive fields against Poggi & Mattoccia 2016, Fu et al. 2017 and
Tosi et al. 2018 as the module docstring states them. The regression test is
``test_lrd_unit_interval_keeps_the_order_of_float32_neighbours``: LRD's map into [0, 1] put the
larger of two LRDs an ulp apart below the smaller one.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.confidence import CONFIDENCE_METHODS, ConfidenceInputs
from cva_confidence_ros.model.baselines import (
    CCNN,
    LFN,
    ConfNet,
    LGCNet,
    ccnn_parameter_count,
    confnet_parameter_count,
    fusion_parameter_count,
    lfn_parameter_count,
)

D, H, W = 8, 6, 5
EPS = 1e-3
SIGMA = 0.1


def _volumes(seed: int, quantised: bool) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    left = rng.random((D, H, W), dtype=np.float32)
    right = rng.random((D, H, W), dtype=np.float32)
    if quantised:  # costs on a grid of 1/4: ties of the two smallest and perfect matches
        left, right = np.round(left * 4) / 4, np.round(right * 4) / 4
    return left.astype(np.float32), right.astype(np.float32)


def _reference(left: np.ndarray, right: np.ndarray) -> dict[str, np.ndarray]:
    """Hu & Mordohai's measures pixel by pixel, float64, with the documented edge values."""
    out = {name: np.zeros((H, W)) for name in ('score', 'pkrn', 'mlm', 'lrd', 'lrc')}
    right_disparity = right.argmin(axis=0)
    for y in range(H):
        for x in range(W):
            curve = left[:, y, x].astype(np.float64)
            d1 = int(curve.argmin())
            c1, c2 = np.sort(curve)[:2]  # naive c2: the second-smallest value
            out['score'][y, x] = -c1
            out['pkrn'][y, x] = (c2 + EPS) / (c1 + EPS)
            weights = np.exp(-curve / (2 * SIGMA**2))
            out['mlm'][y, x] = np.exp(-c1 / (2 * SIGMA**2)) / weights.sum()
            xr = x - d1
            if xr < 0:  # the right partner is outside the image
                out['lrd'][y, x] = 0.0
                out['lrc'][y, x] = -D
            else:
                right_min = float(right[:, y, xr].min())
                out['lrd'][y, x] = (c2 - c1) / (abs(c1 - right_min) + EPS)
                out['lrc'][y, x] = -abs(d1 - right_disparity[y, xr])
    # Column 0: one candidate with a partner, no matching decision (module docstring).
    out['score'][:, 0], out['pkrn'][:, 0], out['mlm'][:, 0], out['lrd'][:, 0] = -1, 1, 1 / D, 0
    return out


@pytest.mark.parametrize('quantised', [False, True])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_measures_follow_hu_mordohai(seed: int, quantised: bool) -> None:
    left, right = _volumes(seed, quantised)
    inputs = ConfidenceInputs(
        cost_volume=left,
        disparity=left.argmin(axis=0).astype(np.float32),
        image=np.zeros((H, W), np.uint8),
        cost_volume_right=right,
        disparity_right=right.argmin(axis=0).astype(np.float32),
    )
    expected = _reference(left, right)
    options = {'pkrn': {'eps': EPS}, 'lrd': {'eps': EPS}, 'mlm': {'sigma': SIGMA}}
    for name, want in expected.items():
        got = CONFIDENCE_METHODS.get(name)(**options.get(name, {}))(inputs)
        assert got.dtype == np.float32 and got.shape == (H, W)
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6, err_msg=name)


def test_tied_minima_and_perfect_matches() -> None:
    # Pixel (0, 1): two equal minima → PKRN 1 (its lowest), LRD 0; pixel (0, 2): a perfect
    # match (c1 = 0) stays finite through eps.
    volume = np.ones((D, 1, 3), np.float32)
    volume[1, 0, 1] = volume[0, 0, 1] = 0.2
    volume[0, 0, 2], volume[1, 0, 2] = 0.0, 0.5
    inputs = ConfidenceInputs(
        cost_volume=volume,
        disparity=volume.argmin(axis=0).astype(np.float32),
        image=np.zeros((1, 3), np.uint8),
        cost_volume_right=volume,
    )
    pkrn = CONFIDENCE_METHODS.get('pkrn')(eps=EPS)(inputs)
    lrd = CONFIDENCE_METHODS.get('lrd')(eps=EPS)(inputs)
    assert pkrn[0, 1] == 1.0 and lrd[0, 1] == 0.0
    assert pkrn[0, 2] == pytest.approx((0.5 + EPS) / EPS, rel=1e-5)
    assert np.isfinite(pkrn).all() and np.isfinite(lrd).all()


def test_lrd_unit_interval_keeps_the_order_of_float32_neighbours() -> None:
    # Two LRDs of the Motorcycle pair (Census-BM, D = 32) one float32 ulp apart: x / (1 + x)
    # with both steps rounded in float32 gave the larger one the smaller unit value.
    low = np.float32(0.12008721)
    high = np.nextafter(low, np.float32(np.inf))
    lrd = CONFIDENCE_METHODS.get('lrd')()
    unit = lrd.to_unit_interval(np.array([[low, high]], np.float32))
    assert unit.dtype == np.float32
    assert unit[0, 0] <= unit[0, 1]
    # And over a dense sweep of the range LRD takes with the default eps.
    values = np.unique(
        np.random.default_rng(0).uniform(0.0, 50.0, 200_000).astype(np.float32)
    )
    swept = lrd.to_unit_interval(values)
    assert np.all(np.diff(swept) >= 0)
    assert lrd.to_unit_interval(np.float32([np.inf, 0.0, -1.0])).tolist() == [1.0, 0.0, 0.0]


@pytest.mark.parametrize('name', ['score', 'pkrn', 'mlm', 'lrc'])
def test_unit_interval_keeps_the_order_of_float32_neighbours(name: str) -> None:
    rng = np.random.default_rng(1)
    low, high = {'score': (-1, 0), 'pkrn': (1, 1001), 'mlm': (0, 1), 'lrc': (-8, 0)}[name]
    values = np.unique(rng.uniform(low, high, 200_000).astype(np.float32))
    unit = CONFIDENCE_METHODS.get(name)().to_unit_interval(values)
    assert np.all(np.diff(unit) >= 0)


def _count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def test_baseline_layers_and_parameter_counts() -> None:
    ccnn = CCNN(64)
    convs = [m for m in ccnn.tower if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.padding) for c in convs] == [
        (1, 64, (3, 3), (0, 0))
    ] + [(64, 64, (3, 3), (0, 0))] * 3
    head = [m for m in ccnn.head if isinstance(m, torch.nn.Conv2d)]
    assert [(c.out_channels, c.kernel_size) for c in head] == [(100, (1, 1)), (100, (1, 1)),
                                                                (1, (1, 1))]
    assert _count(ccnn) == ccnn_parameter_count() == 128_125
    assert _count(LFN(64)) == lfn_parameter_count()
    lgc = LGCNet(64)
    assert _count(lgc.confnet) == confnet_parameter_count()
    assert _count(lgc.fusion) == fusion_parameter_count()
    encoders = [e.out_channels for e in ConfNet().encoders]
    assert encoders == [64, 128, 256, 512]


def test_ccnn_sees_a_9x9_patch_and_lgc_net_17x17() -> None:
    torch.manual_seed(0)
    ccnn = CCNN(64).eval()
    disparity = torch.rand(1, 1, 21, 21, requires_grad=True)
    ccnn.forward_logits(disparity, disparity.detach())[0, 0, 6, 6].backward()
    assert disparity.grad is not None
    rows, cols = np.nonzero(disparity.grad[0, 0].numpy())
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (6, 14, 6, 14)
    # LGC-Net's local path (CCNN, then the fusion's local tower) reaches 8 px each side.
    assert LGCNet.margin == 8 and CCNN.margin == 4
