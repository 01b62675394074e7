"""``StereoPipeline`` and ``PipelineConfig``: a small real pair, and bad configs and images."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

#: A stereo pair (left, right) of uint8 images: the ``slanted_pair`` fixture (conftest).
Pair = tuple[np.ndarray, np.ndarray]

def _pair(height: int = 32, width: int = 64, shift: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (height, width), dtype=np.uint8)
    return left, np.roll(left, -shift, axis=1)


def _pipeline(**changes: object) -> StereoPipeline:
    config = PipelineConfig(matcher='census_bm', max_disparity=16, confidence_method='pkrn')
    return StereoPipeline(config.replace(**changes))


def test_downsampled_pair_through_the_real_matcher():
    result = _pipeline(downsample=2).process(*_pair())
    assert result.disparity.shape == result.confidence.shape == (16, 32)
    assert result.scale == 0.5
    inner = result.disparity[4:-4, 8:-8]
    assert np.nanmedian(inner) == pytest.approx(2.0, abs=0.05)  # the 4 px shift at half size


def test_subpixel_moves_the_integer_disparity_by_at_most_half_a_pixel():
    left, right = _pair()
    integer = _pipeline(subpixel='none').process(left, right)
    assert np.all(integer.disparity == np.round(integer.disparity))
    assert 'subpixel' not in integer.timings_ms
    assert integer.disparity.dtype == np.float32
    for method in ('equiangular', 'parabola'):
        refined = _pipeline(subpixel=method).process(left, right)
        step = refined.disparity - integer.disparity
        assert np.all(np.abs(step) <= 0.5) and np.any(step != 0)
        np.testing.assert_array_equal(refined.confidence, integer.confidence)
        assert refined.timings_ms['subpixel'] >= 0
    assert PipelineConfig().subpixel == 'equiangular'
    assert PipelineConfig().disparity_step == 0.0
    assert PipelineConfig(subpixel='none').disparity_step == 1.0
    with pytest.raises(ConfigError, match="subpixel must be one of .*'cubic'"):
        PipelineConfig(subpixel='cubic')


def test_subpixel_keeps_the_left_right_check():
    left, right = _pair()
    checked = _pipeline(lr_check=True).process(left, right)
    unchecked = _pipeline(lr_check=True, subpixel='none').process(left, right)
    np.testing.assert_array_equal(np.isnan(checked.disparity), np.isnan(unchecked.disparity))
    assert np.isnan(checked.disparity).any()


def test_speckle_filter_drops_small_regions_of_the_kept_pixels():
    from scipy import ndimage

    left, right = _pair()
    left[:, 20:24] = 128  # a texture-less strip: disparities that agree with nothing
    right = np.roll(left, -4, axis=1)
    plain = _pipeline(subpixel='none', speckle_size=0).process(left, right)
    assert 'speckle' not in plain.timings_ms
    np.testing.assert_array_equal(
        plain.valid, np.isfinite(plain.disparity) & (plain.confidence >= 0.5)
    )
    filtered = _pipeline(subpixel='none', speckle_size=12, speckle_range=0.0).process(left, right)
    np.testing.assert_array_equal(filtered.disparity, plain.disparity)
    np.testing.assert_array_equal(filtered.confidence, plain.confidence)
    assert filtered.timings_ms['speckle'] >= 0
    # With range 0 a region is a 4-connected run of one integer disparity among the kept
    # pixels: scipy's labelling, value by value, gives the same answer.
    expected = np.zeros_like(plain.valid)
    for value in np.unique(plain.disparity[plain.valid]):
        labels, count = ndimage.label(plain.valid & (plain.disparity == value))
        sizes = np.bincount(labels.ravel())
        expected |= (labels > 0) & (sizes[labels] > 12)
    np.testing.assert_array_equal(filtered.valid, expected)
    assert 0 < filtered.valid.sum() < plain.valid.sum()
    assert filtered.speckle_fraction == (plain.valid.sum() - filtered.valid.sum()) / 32 / 64
    assert plain.speckle_fraction == 0.0
    assert PipelineConfig().speckle_size == 100 and PipelineConfig().speckle_range == 1.0


@pytest.mark.parametrize(
    ('changes', 'message'),
    [
        ({'max_disparity': 'abc'}, 'max_disparity must be an integer'),
        ({'max_disparity': None}, 'max_disparity must be an integer'),
        ({'max_disparity': 64.7}, 'max_disparity must be an integer'),
        ({'max_disparity': True}, 'max_disparity must be an integer'),
        ({'downsample': 2.0}, 'downsample must be 1, 2 or 4'),
        ({'confidence_threshold': 'x'}, 'confidence_threshold must be a number'),
        ({'confidence_threshold': float('nan')}, 'confidence_threshold must be a number'),
        ({'tile_budget_mb': 'x'}, 'tile_budget_mb must be a finite number'),
        ({'tile_budget_mb': float('nan')}, 'tile_budget_mb must be a finite number'),
        ({'tile_budget_mb': float('inf')}, 'tile_budget_mb must be a finite number'),
        ({'speckle_size': -1}, 'speckle_size must be an integer in \\[0, 1000000\\]'),
        ({'speckle_size': 10.0}, 'speckle_size must be an integer'),
        ({'speckle_range': float('nan')}, 'speckle_range must be a number in \\[0, 1024\\]'),
        ({'speckle_range': -1.0}, 'speckle_range must be a number'),
        ({'roi_top': float('nan')}, 'roi_top must be a number in \\[0, 1\\]'),
        ({'roi_bottom': 1.5}, 'roi_bottom must be a number in \\[0, 1\\]'),
        ({'roi_top': '0.2'}, 'roi_top must be a number'),
        ({'roi_top': 0.6, 'roi_bottom': 0.6},
         'roi_top must be smaller than roi_bottom .*got roi_top = 0.6, roi_bottom = 0.6'),
    ],
)
def test_config_refuses_wrong_types_and_non_finite_values(changes, message):
    with pytest.raises(ConfigError, match=message):
        PipelineConfig(confidence_method='pkrn').replace(**changes)


@pytest.mark.parametrize('dtype', [np.int64, np.bool_])
def test_bad_images_are_named_before_the_resize(dtype):
    left, right = _pair()
    with pytest.raises(InputError, match='image must be uint8'):
        _pipeline(downsample=2).process(left.astype(dtype), right.astype(dtype))


def test_float_images_in_0_255_are_taken_as_intensities_before_the_resize():
    left, right = _pair()
    pipeline = _pipeline(downsample=2)
    as_float = pipeline.process(left.astype(np.float16), right.astype(np.float16))
    np.testing.assert_array_equal(as_float.disparity, pipeline.process(left, right).disparity)


def test_images_smaller_than_the_downsample_factor():
    left, right = _pair(3, 64)
    with pytest.raises(InputError, match='cannot be shrunk by downsample = 4'):
        _pipeline(downsample=4).process(left, right)


def test_expected_kept_error_only_for_a_probabilistic_method():
    left, right = _pair(height=48, width=96)
    handcrafted = _pipeline(downsample=1).process(left, right)
    assert handcrafted.probabilistic is False and handcrafted.expected_kept_error is None

    # The shipped CVA-Net-Fast weights (D = 64): its output is a probability.
    network = _pipeline(
        confidence_method='cva_net_fast', max_disparity=64, confidence_threshold=0.3
    ).process(left, right)
    assert network.probabilistic is True
    kept = network.valid
    assert 0 < kept.sum() < kept.size
    assert network.kept_fraction == pytest.approx(kept.mean())
    expected = 1.0 - network.confidence[kept].astype(np.float64).mean()
    assert network.expected_kept_error == pytest.approx(expected, rel=1e-9)
    # Nothing kept: no estimate rather than a made-up one.
    none_kept = _pipeline(
        confidence_method='cva_net_fast', max_disparity=64, confidence_threshold=1.0
    ).process(np.zeros_like(left), np.zeros_like(right))
    assert none_kept.kept_fraction == 0.0 and none_kept.expected_kept_error is None



@pytest.mark.parametrize('method', ['pkrn', 'cva_net_fast'])
def test_the_region_of_interest_is_the_whole_image_result_there(
    method: str, slanted_pair: Pair
) -> None:
    # Census-BM's windows and the networks' extracts reach no further than ROI_MARGIN rows, so
    # inside the region everything equals the whole-image result; outside nothing is computed.
    left, right = slanted_pair
    base = {'confidence_method': method, 'speckle_size': 0, 'device': 'cpu', 'max_disparity': 64}
    whole = _pipeline(**base).process(left, right)
    part = _pipeline(**base, roi_top=0.3, roi_bottom=0.75).process(left, right)
    y0, y1 = part.rows
    assert (y0, y1) == (28, 72) and whole.rows == (0, 96)
    for name in ('disparity', 'confidence', 'raw_confidence', 'valid'):
        np.testing.assert_array_equal(getattr(part, name)[y0:y1], getattr(whole, name)[y0:y1],
                                      err_msg=name)
    outside = np.r_[0:y0, y1:96]
    assert np.isnan(part.disparity[outside]).all() and np.isnan(part.raw_confidence[outside]).all()
    assert (part.confidence[outside] == 0.0).all() and not part.valid[outside].any()
    assert part.disparity.shape == part.confidence.shape == whole.disparity.shape
    # The kept share is that of the region (what /diagnostics reports).
    assert part.kept_fraction == pytest.approx(whole.valid[y0:y1].mean())


def test_the_region_near_the_image_edges_and_downsampled(slanted_pair: Pair) -> None:
    left, right = slanted_pair
    # Rows at the processed resolution (48 at downsample 2), one row at least.
    config = PipelineConfig(confidence_method='pkrn', roi_top=0.5, roi_bottom=0.51)
    assert config.roi_rows(48) == (24, 25) and config.roi_rows(1) == (0, 1)
    assert PipelineConfig(confidence_method='pkrn', roi_top=0.0, roi_bottom=0.1).roi_rows(96) \
        == (0, 10)
    part = _pipeline(roi_bottom=0.25, downsample=2, speckle_size=0).process(left, right)
    whole = _pipeline(downsample=2, speckle_size=0).process(left, right)
    assert part.rows == (0, 12)
    np.testing.assert_array_equal(part.disparity[:12], whole.disparity[:12])
    assert np.isnan(part.disparity[12:]).all()
    # With the speckle filter the region's kept pixels are a subset of the whole image's
    # candidates (a region cut by the edge of the region of interest may be dropped).
    part = _pipeline(roi_top=0.5).process(left, right)
    assert not part.valid[:48].any() and part.valid[48:].any()


def test_census_sgm_in_a_region_of_interest_differs_only_near_its_edges(
    slanted_pair: Pair,
) -> None:
    # SGM's vertical and diagonal paths start at the edge of the margin, not of the image.
    left, right = slanted_pair
    base = {'matcher': 'census_sgm', 'speckle_size': 0}
    whole = _pipeline(**base).process(left, right)
    part = _pipeline(**base, roi_top=0.3, roi_bottom=0.75).process(left, right)
    y0, y1 = part.rows
    same = part.disparity[y0:y1] == whole.disparity[y0:y1]
    assert same.mean() > 0.97


# A fresh interpreter (nothing compiled or loaded from numba's cache yet): for each
# configuration a new pipeline is warmed up, then its first frame (another size, colour) may
# add no signature to any numba dispatcher of the package, i.e. compile or load nothing.
_FIRST_FRAME_COMPILES_NOTHING = r"""
import json
import sys

from numba.core.registry import CPUDispatcher
import numpy as np

from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline


def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith('cva_confidence_ros'):
            for attr, value in list(vars(module).items()):
                if isinstance(value, CPUDispatcher):
                    found[f'{name}.{attr}'] = len(value.signatures)
    return found


rng = np.random.default_rng(1)
texture = rng.integers(0, 256, (40, 110, 3), dtype=np.uint8)
left, right = texture[:, 6:].copy(), texture[:, :104].copy()
added = {}
for changes in json.loads(sys.argv[1]):
    pipeline = StereoPipeline(PipelineConfig(device='cpu', **changes))
    pipeline.warm_up()
    before = signatures()
    pipeline.process(left, right)
    new = {k: n - before.get(k, 0) for k, n in signatures().items() if n > before.get(k, 0)}
    added[changes['confidence_method']] = new
print(json.dumps(added))
"""


def test_after_warm_up_the_first_frame_compiles_no_numba_kernel() -> None:
    # The old warm-up ran the matcher only: the first frame compiled (or loaded) the
    # winner-takes-all, sub-pixel and speckle kernels, the hand-crafted measures' and
    # CVA-Net-Fast's curve kernel, 2–5 s with an empty numba cache.
    import json
    import subprocess
    import sys

    configs = [
        {'confidence_method': 'cva_net_fast'},
        {'matcher': 'census_sgm', 'confidence_method': 'pkrn', 'lr_check': True,
         'downsample': 2, 'max_disparity': 32, 'roi_top': 0.25},
        {'matcher': 'census_bm', 'confidence_method': 'cva_net', 'cva_stride': 2,
         'cva_cascade': 'pkrn', 'max_disparity': 64, 'roi_bottom': 0.3},
        {'matcher': 'mccnn_fast', 'confidence_method': 'lrd', 'max_disparity': 32,
         'subpixel': 'parabola'},
    ]
    run = subprocess.run(
        [sys.executable, '-c', _FIRST_FRAME_COMPILES_NOTHING, json.dumps(configs)],
        capture_output=True, text=True, timeout=300, check=False,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    added = json.loads(run.stdout.strip().splitlines()[-1])
    assert added == {config['confidence_method']: {} for config in configs}


def test_warm_up_leaves_no_counts_and_keeps_the_last_mccnn_pair() -> None:
    from cva_confidence_ros.matching import mccnn_fast

    fast = StereoPipeline(PipelineConfig(device='cpu'))
    evaluator = fast._method.evaluator  # type: ignore[attr-defined]
    fast.warm_up()
    assert evaluator.path_counts == {'tile': 0, 'fused': 0, 'extracts': 0}
    assert evaluator.flops_done == 0.0
    fast.process(*_pair(width=96))
    assert sum(evaluator.path_counts.values()) > 0  # the counters do count real frames

    left, right = _pair(width=48)
    mccnn = _pipeline(matcher='mccnn_fast')
    mccnn.process(left, right)
    key = mccnn_fast._FEATURES.key(left, right, 'cpu', '')
    assert mccnn_fast._FEATURES.get(key) is not None
    mccnn.warm_up()
    assert mccnn_fast._FEATURES.get(key) is not None


def test_warm_up_runs_cva_net_on_a_cpu_on_a_small_window(monkeypatch: pytest.MonkeyPatch) -> None:
    from cva_confidence_ros.confidence.cva_net import CVANetConfidence

    seen: list[tuple[int, int]] = []
    original = CVANetConfidence.__call__

    def spy(self: CVANetConfidence, inputs):  # type: ignore[no-untyped-def]
        seen.append(inputs.shape)
        return original(self, inputs)

    monkeypatch.setattr(CVANetConfidence, '__call__', spy)
    paper = StereoPipeline(PipelineConfig(confidence_method='cva_net', device='cpu'))
    paper.warm_up()
    # 2e9 multiply-adds (D = 64, the 12-pixel border counted): a 6×6 window takes 1.84e9,
    # 7×7 would take 2.35e9
    assert seen == [(6, 6)]
    seen.clear()
    fast = StereoPipeline(PipelineConfig(confidence_method='cva_net_fast', device='cpu'))
    fast.warm_up()
    assert seen == [(16, 64 + 16)]  # the light network sees the whole synthetic pair


def test_warm_up_ignores_the_mask_of_real_images(tmp_path) -> None:  # type: ignore[no-untyped-def]
    import cv2

    mask = np.full((32, 64), 255, np.uint8)
    mask[:, :8] = 0
    cv2.imwrite(str(tmp_path / 'mask.png'), mask)
    pipeline = _pipeline(mask_path=str(tmp_path / 'mask.png'))
    pipeline.warm_up()  # 16 × 32 synthetic pair: the 32 × 64 mask does not fit it
    assert pipeline._reduced is None
    result = pipeline.process(*_pair())
    assert not result.valid[:, :8].any() and result.valid[:, 8:].any()


@pytest.mark.parametrize('method', ['pkrn', 'lrd'])
def test_a_method_that_needs_two_disparities_is_refused_at_max_disparity_1(method: str) -> None:
    # It used to be built, and then every frame failed with an InputError about the volume.
    with pytest.raises(ConfigError, match=f'{method} .* needs max_disparity ≥ 2; got 1'):
        _pipeline(confidence_method=method, max_disparity=1)
    result = _pipeline(confidence_method='mlm', max_disparity=1).process(*_pair())
    np.testing.assert_array_equal(result.raw_confidence, 1.0)  # one disparity: all certain
