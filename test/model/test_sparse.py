"""Sparse evaluation of CVA-Net: exact where it should be, within its AUC budget elsewhere."""

from __future__ import annotations

from pathlib import Path

from light_net_test_utils import with_data_bn
import numpy as np
import pytest
import torch
from torch import nn

from cva_confidence_ros.confidence import ConfidenceInputs, compute_confidence
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
from cva_confidence_ros.metrics import kitti_error, roc_auc
from cva_confidence_ros.model import (
    CVANet,
    SparseConfig,
    SparseEvaluator,
    fold_batchnorm,
    load_weights,
    predict_confidence,
    sparse_confidence,
)
from cva_confidence_ros.model.sparse import (
    CALIBRATION_RATIO,
    MIN_CALIBRATION,
    cascade_selection,
    grid_offset,
    joint_bilateral_fill,
    monotone_map,
)

DEPTH, HEIGHT, WIDTH = 16, 20, 28
SHIPPED = Path(__file__).resolve().parents[2] / 'models' / 'cvanet_census_bm_d64.pt'
#: AUC budget of the approximate paths on the fixed synthetic scene, as the share of the gap
#: between the exact network and PKRN alone (the cheap measure they fall back on) that they may
#: lose: (AUC − AUC_exact) / (AUC_pkrn − AUC_exact). A ratio to the exact AUC would depend on how
#: good the shipped weights are (the GPU-trained census_bm weights made every ratio 1.2–3.0× on
#: this scene, where PKRN alone is 3.4×); the share of the gap does not. Measured with those
#: weights (seed 7, 24×160): stride 2/4/8 0.08/0.26/0.41, pkrn 0.5 → 0.40, pkrn 0.25 with
#: stride 2 → 0.79, with stride 8 → 0.84.
# Shares of the AUC gap between the exact network and its PKRN fallback that a sparse map may
# lose on the fixed scene below. PKRN's column-0 rule (handcrafted) made the fallback better
# there (AUC 0.057 → 0.043 on this 160 px wide scene at D = 64), which narrowed the gap: the
# stride-4 map, unchanged at 0.0271 against the exact 0.0167, went from 0.26 to 0.40 of it.
AUC_BUDGET = 0.45
AUC_BUDGET_COARSE = 0.90
APPROXIMATE = (
    SparseConfig(stride=2),
    SparseConfig(stride=4),
    SparseConfig(stride=8),
    SparseConfig(cascade='pkrn', cascade_fraction=0.5),
    SparseConfig(cascade='pkrn', cascade_fraction=0.25, stride=2),
    SparseConfig(cascade='pkrn', cascade_fraction=0.25, stride=8),
)


pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _volume(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    truth = rng.integers(0, DEPTH, size=(HEIGHT, WIDTH))
    d = np.arange(DEPTH)[:, None, None]
    volume = np.minimum(1.0, np.abs(d - truth[None]) / 4.0) + rng.normal(
        0, 0.1, (DEPTH, HEIGHT, WIDTH)
    )
    return np.clip(volume, 0.0, 1.0).astype(np.float32)


@pytest.fixture(scope='module')
def net() -> nn.Module:
    """A seeded network with data-driven BN statistics, folded for inference."""
    torch.manual_seed(0)
    model = with_data_bn(CVANet(DEPTH), [_volume(seed + 10) for seed in range(3)])
    return fold_batchnorm(model)


class _PlainNet(nn.Module):
    """A network with only the forward contract (like a distilled light net): no split."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner = inner
        self.max_disparity = inner.max_disparity

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        return self.inner(volume)


@pytest.mark.parametrize('path', ['auto', 'tile', 'fused', 'extracts'])
def test_every_pixel_equals_exact(net, path):
    volume = _volume()
    exact = predict_confidence(net, volume)
    evaluator = SparseEvaluator(net, tile_budget_mb=2.0, path=path)  # several tiles
    np.testing.assert_allclose(evaluator(volume), exact, atol=1e-4, rtol=0)
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    result = evaluator.confidence(volume, image, wta_disparity(volume), SparseConfig())
    np.testing.assert_allclose(result.confidence, exact, atol=1e-4, rtol=0)
    assert result.evaluated.all() and not result.decided.any()


@pytest.mark.parametrize('stride', [2, 4, 8])
def test_strided_grid_keeps_network_values(net, stride):
    volume = _volume(1)
    exact = predict_confidence(net, volume)
    image = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    for model in (net, _PlainNet(net)):
        evaluator = SparseEvaluator(model)
        result = evaluator.confidence(
            volume, image, wta_disparity(volume), SparseConfig(stride=stride)
        )
        offset = grid_offset(stride)
        grid = np.zeros((HEIGHT, WIDTH), bool)
        grid[offset::stride, offset::stride] = True
        np.testing.assert_array_equal(result.evaluated, grid)
        np.testing.assert_allclose(result.confidence[grid], exact[grid], atol=1e-4, rtol=0)
        assert np.all((result.confidence > 0) & (result.confidence < 1))
    assert result.network_share == pytest.approx(grid.mean())


def test_auto_path_follows_operation_counts(net):
    volume = _volume()
    evaluator = SparseEvaluator(net)
    dense = np.ones((HEIGHT, WIDTH), bool)
    evaluator(volume, dense)
    assert evaluator.path_counts['tile'] == 1
    single = np.zeros_like(dense)
    single[5, 5] = True
    evaluator(volume, single)
    assert evaluator.path_counts['extracts'] == 1
    quarter = np.zeros_like(dense)
    quarter[::2, ::2] = True
    evaluator(volume, quarter)
    assert evaluator.path_counts['fused'] == 1
    with pytest.raises(ConfigError, match='fusion_features'):
        SparseEvaluator(_PlainNet(net), path='fused')


@pytest.mark.parametrize('path', ['tile', 'extracts'])
def test_progress_reports_pixels_up_to_the_total(net, path):
    volume = _volume()
    evaluator = SparseEvaluator(net, tile_budget_mb=2.0, path=path)  # several tiles
    reports: list[tuple[int, int]] = []
    evaluator.progress = lambda done, total: reports.append((done, total))
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[::3, ::2] = True
    evaluator(volume, mask)
    done = [d for d, _ in reports]
    assert len(reports) > 1 and done == sorted(done)
    assert {t for _, t in reports} == {int(mask.sum())} and done[-1] == int(mask.sum())
    reports.clear()
    ys, xs = np.nonzero(np.ones((HEIGHT, WIDTH), bool))
    evaluator.at(volume, ys, xs)
    batch = evaluator.extract_batch  # bounded by the 2 MB budget
    assert reports[-1] == (ys.size, ys.size) and len(reports) == -(-ys.size // batch)


def test_bf16_within_tolerance(net):
    volume = _volume(2)[:, :12, :12]
    exact = predict_confidence(net, volume)
    bf16 = SparseEvaluator(net, precision='bf16')(volume)
    # bfloat16 keeps 8 bits of mantissa; through 18 layers of this random network the
    # confidence moves by ≈ 0.01 on average and single pixels by up to ≈ 0.06 where the CPU has
    # native bf16 dot products (AVX512-BF16: other rounding than the float32 fallback), so the
    # bound is on the mean, with a loose one on each pixel.
    difference = np.abs(bf16 - exact)
    assert difference.mean() < 0.02 and difference.max() < 0.1
    assert np.corrcoef(bf16.ravel(), exact.ravel())[0, 1] > 0.98


def test_fp16_needs_cuda(net):
    if torch.cuda.is_available():
        pytest.skip('CUDA present: fp16 is allowed')
    with pytest.raises(ConfigError, match='fp16'):
        SparseEvaluator(net, precision='fp16')


@pytest.mark.skipif(not torch.cuda.is_available(), reason='needs CUDA')
@pytest.mark.parametrize('precision', ['fp16', 'bf16'])
def test_cuda_reduced_precision(net, precision):
    volume = _volume(2)
    exact = predict_confidence(net, volume)
    result = SparseEvaluator(net, device='cuda', precision=precision)(volume)
    np.testing.assert_allclose(result, exact, atol=0.05, rtol=0)


@pytest.mark.parametrize(
    'changes, field',
    [
        ({'stride': 3}, 'cva_stride'),
        ({'cascade': 'mlm'}, 'cva_cascade'),
        ({'cascade_fraction': 0.0}, 'cva_cascade_fraction'),
        ({'cascade_fraction': 1.5}, 'cva_cascade_fraction'),
        ({'precision': 'int8'}, 'cva_precision'),
        ({'path': 'fast'}, 'path'),
    ],
)
def test_bad_config_names_field(changes, field):
    with pytest.raises(ConfigError, match=field):
        SparseConfig(**changes)


@pytest.mark.parametrize(
    'changes, field',
    [
        ({'stride': 2.0}, 'cva_stride'),
        ({'stride': True}, 'cva_stride'),
        ({'stride': '2'}, 'cva_stride'),
        ({'cascade_fraction': True}, 'cva_cascade_fraction'),
        ({'cascade_fraction': '0.5'}, 'cva_cascade_fraction'),
        ({'cascade_fraction': float('nan')}, 'cva_cascade_fraction'),
        ({'cascade_fraction': None}, 'cva_cascade_fraction'),
    ],
    ids=repr,
)
def test_config_refuses_wrong_types(changes, field):
    with pytest.raises(ConfigError, match=field):
        SparseConfig(**changes)


def test_config_takes_numpy_numbers():
    config = SparseConfig(stride=np.int64(4), cascade='pkrn', cascade_fraction=np.float32(0.5))
    assert config.stride == 4 and config.cascade_fraction == 0.5
    assert SparseConfig(cascade_fraction=1).cascade_fraction == 1


@pytest.mark.parametrize(
    'budget', [0, -1.0, float('nan'), float('inf'), '1', None, True], ids=repr
)
def test_evaluator_checks_tile_budget_at_construction(net, budget):
    with pytest.raises(ConfigError, match='tile_budget_mb must be a finite number > 0'):
        SparseEvaluator(net, tile_budget_mb=budget)


def test_evaluator_takes_a_numpy_tile_budget(net):
    evaluator = SparseEvaluator(net, tile_budget_mb=np.float32(64.0))
    assert evaluator.tile_budget_mb == 64.0 and type(evaluator.tile_budget_mb) is float


def test_step_edge_is_respected():
    height, width, stride = 24, 40, 4
    image = np.zeros((height, width), np.uint8)
    image[:, 21:] = 200  # an edge between grid columns 17 and 21
    disparity = np.where(image > 0, 20.0, 5.0).astype(np.float32)
    truth = np.where(image > 0, 1.0, -1.0)
    offset = grid_offset(stride)
    rows, cols = np.arange(offset, height, stride), np.arange(offset, width, stride)
    samples = truth[np.ix_(rows, cols)]
    known = np.ones_like(samples, bool)
    filled = joint_bilateral_fill(samples, known, stride, image, disparity)
    np.testing.assert_array_equal(filled[np.ix_(rows, cols)], samples)  # grid kept exactly
    np.testing.assert_allclose(filled, truth, atol=1e-6)  # nothing crosses the edge
    # Without the edge terms the same samples bleed across it.
    flat = joint_bilateral_fill(
        samples, known, stride, np.zeros_like(image), np.zeros_like(disparity)
    )
    assert np.abs(flat - truth).max() > 0.3
    # Smooth data are interpolated, not copied: away from the borders a ramp stays a ramp.
    ramp = np.tile(np.linspace(0, 1, width), (height, 1))
    smooth = joint_bilateral_fill(
        ramp[np.ix_(rows, cols)], known, stride, np.zeros_like(image), np.zeros_like(disparity)
    )
    assert np.abs(smooth - ramp)[:, cols[1]:cols[-2]].max() < 0.03


def test_unknown_samples_are_skipped():
    image = np.zeros((8, 8), np.uint8)
    samples = np.array([[1.0, 5.0], [1.0, 1.0]])
    known = np.array([[True, False], [True, True]])
    filled = joint_bilateral_fill(samples, known, 4, image, np.zeros((8, 8), np.float32))
    np.testing.assert_allclose(filled, 1.0)
    with pytest.raises(InputError, match='grid samples'):
        joint_bilateral_fill(samples[:1], known[:1], 4, image, np.zeros((8, 8), np.float32))


def test_monotone_map():
    x = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    y = np.array([0.0, 2.0, 1.0, 3.0, 3.0, 5.0])
    mapped = monotone_map(x, y, np.linspace(-0.5, 1.5, 201))
    assert np.all(np.diff(mapped) > 0)  # strictly increasing
    fit = monotone_map(x, y, x) - 1e-3 * x
    # Steps {0.1, 0.2} → 1.5 (centre 0.15); the map is linear between step centres.
    np.testing.assert_allclose(fit, [0.0, 1.0, 2.0, 3.0, 3.0, 5.0], atol=1e-12)
    with pytest.raises(InputError):
        monotone_map(np.array([]), np.array([]), x)


def test_cascade_selection_takes_the_least_confident():
    rank = np.linspace(0, 1, 400).reshape(20, 20)
    candidates = np.ones_like(rank, bool)
    undecided, calibration = cascade_selection(rank, candidates, 0.25)
    assert undecided.sum() == 100
    assert rank[undecided].max() < rank[~undecided].min()
    assert calibration.sum() == max(MIN_CALIBRATION, 100 // CALIBRATION_RATIO)
    assert not (calibration & undecided).any()
    assert rank[calibration].min() == rank[~undecided].min() and rank[calibration].max() == 1.0
    # On a stride grid only grid pixels are calibration candidates.
    grid = np.zeros_like(candidates)
    grid[::4, ::4] = True
    sparse_undecided, sparse_calibration = cascade_selection(rank, grid, 0.25)
    assert (sparse_calibration <= grid).all()
    # 15 decided grid pixels, fewer than MIN_CALIBRATION: all of them calibrate.
    np.testing.assert_array_equal(sparse_calibration, grid & ~sparse_undecided)
    everything, none = cascade_selection(rank, candidates, 1.0)
    assert everything.all() and not none.any()


@pytest.fixture(scope='module')
def scene():
    """A fixed synthetic scene, census_bm at D = 64, and the exact shipped-network map."""
    if not SHIPPED.exists():
        pytest.skip('shipped weights not found')
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one reduction order for the exact map and the sparse evaluations
    sample = synthetic_pair(7, height=24, width=160, max_disparity=64)
    volume = compute_cost_volume(sample.left, sample.right, 'census_bm', 64)
    disparity = wta_disparity(volume)
    net, _ = load_weights(SHIPPED, matcher='census_bm', max_disparity=64)
    evaluator = SparseEvaluator(net)
    exact = evaluator(volume)
    wrong = kitti_error(disparity, sample.disparity)
    cheap = compute_confidence('pkrn', ConfidenceInputs(volume, disparity, sample.left))
    yield sample, volume, disparity, evaluator, exact, wrong, cheap
    torch.set_num_threads(threads)


@pytest.mark.parametrize('config', APPROXIMATE, ids=str)
def test_auc_budget_on_fixed_scene(scene, config):
    sample, volume, disparity, _, exact, wrong, cheap = scene
    # The result depends on the network only through its values at the evaluated pixels,
    # which equal the exact map's (tests above), so the exact map stands in for the network.
    result = sparse_confidence(
        lambda _volume, _mask: exact, volume, sample.left, disparity, config, cheap
    )
    auc_exact, auc_cheap = roc_auc(exact, wrong), roc_auc(cheap, wrong)
    assert auc_cheap > 1.5 * auc_exact  # the scene separates the network from its fallback
    lost = (roc_auc(result.confidence, wrong) - auc_exact) / (auc_cheap - auc_exact)
    fine = config.cascade == 'none' and config.stride <= 4
    assert lost <= (AUC_BUDGET if fine else AUC_BUDGET_COARSE)
    assert result.network_share < 0.6


def test_real_sparse_run_matches_the_lookup(scene):
    sample, volume, disparity, evaluator, exact, _, cheap = scene
    config = SparseConfig(stride=4, cascade='pkrn', cascade_fraction=0.5)
    real = evaluator.confidence(volume, sample.left, disparity, config, cheap)
    lookup = sparse_confidence(
        lambda _volume, _mask: exact, volume, sample.left, disparity, config, cheap
    )
    np.testing.assert_allclose(real.confidence, lookup.confidence, atol=1e-4, rtol=0)
    np.testing.assert_array_equal(real.evaluated, lookup.evaluated)


def test_the_evaluator_leaves_the_callers_module_as_it_was() -> None:
    torch.manual_seed(0)
    folded = fold_batchnorm(CVANet(max_disparity=16).eval())
    folded.train()  # e.g. a module the caller goes on training
    evaluator = SparseEvaluator(folded)
    # Before: the caller's module was switched to eval mode (and moved to the device).
    assert folded.training
    assert evaluator.net is not folded and not evaluator.net.training
    volume = np.random.default_rng(0).random((16, 9, 11), dtype=np.float32)
    expected = predict_confidence(folded.eval(), volume)
    np.testing.assert_allclose(evaluator(volume), expected, atol=1e-5)
