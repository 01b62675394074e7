"""MC-CNN fast with the pretrained weights of the mccnn package, on 40×60 images."""

from __future__ import annotations

from pathlib import Path

from matching_test_utils import shifted_pair
import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, ModelError
from cva_confidence_ros.matching import compute_cost_volume, mccnn_fast, mccnn_net, wta_disparity

HEIGHT, WIDTH, SHIFT, DEPTH = 40, 60, 5, 12


@pytest.fixture(scope='module')
def pair() -> tuple[np.ndarray, np.ndarray]:
    return shifted_pair(HEIGHT, WIDTH, SHIFT, seed=11, colour=True)


def test_network_shape_parameters_and_unit_features() -> None:
    network = mccnn_net.load_network()
    # 1→64, then four 64→64 3×3 convolutions with biases
    assert sum(p.numel() for p in network.parameters()) == (9 + 1) * 64 + 4 * (9 * 64 + 1) * 64
    assert mccnn_net.load_network() is network  # loaded once per process
    image = np.random.default_rng(0).integers(0, 256, (7, 9), dtype=np.uint8)
    features = mccnn_net.extract_features(network, [image, image], torch.device('cpu'))
    assert tuple(features.shape) == (2, 64, 7, 9)  # padding keeps the image size
    torch.testing.assert_close(features.norm(dim=1), torch.ones(2, 7, 9))


def test_normalisation_is_zero_mean_unit_variance() -> None:
    image = np.array([[0, 255], [255, 0]], np.uint8)
    np.testing.assert_allclose(mccnn_net.normalise_image(image), [[-1, 1], [1, -1]], atol=1e-6)
    assert not mccnn_net.normalise_image(np.full((3, 3), 9, np.uint8)).any()


def test_volume_range_outside_cost_and_shift(pair: tuple[np.ndarray, np.ndarray]) -> None:
    left, right = pair
    volume = compute_cost_volume(left, right, 'mccnn_fast', DEPTH)
    assert volume.shape == (DEPTH, HEIGHT, WIDTH) and volume.dtype == np.float32
    assert 0.0 <= volume.min() and volume.max() <= 1.0
    for d in range(DEPTH):
        assert np.all(volume[d, :, :d] == 1.0)
    disparity = wta_disparity(volume)
    # Identical 11×11 patches give nearly identical features away from the borders (not
    # exactly: each image is standardised with its own mean and deviation).
    assert np.all(disparity[5:-5, SHIFT + 5:-5] == SHIFT)
    assert np.all(volume[SHIFT, 5:-5, SHIFT + 5:-5] < 1e-3)


def test_right_view_pairs_the_same_features(pair: tuple[np.ndarray, np.ndarray]) -> None:
    left, right = pair
    vol_left = compute_cost_volume(left, right, 'mccnn_fast', DEPTH)
    vol_right = compute_cost_volume(left, right, 'mccnn_fast', DEPTH, view='right')
    for d in range(DEPTH):
        np.testing.assert_allclose(vol_right[d, :, :WIDTH - d], vol_left[d, :, d:], atol=1e-6)
        assert np.all(vol_right[d, :, WIDTH - d:] == 1.0)


def test_right_view_reuses_the_features_of_the_pair(
    pair: tuple[np.ndarray, np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    left, right = pair
    calls = []
    original = mccnn_net.extract_features

    def counting(*args: object, **kwargs: object) -> torch.Tensor:
        calls.append(1)
        return original(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(mccnn_net, 'extract_features', counting)
    fresh = left.copy()
    fresh[0, 0] ^= 1  # a pair the cache has not seen
    compute_cost_volume(fresh, right, 'mccnn_fast', 4)
    compute_cost_volume(fresh, right, 'mccnn_fast', 4, view='right')
    assert len(calls) == 1
    compute_cost_volume(left, right, 'mccnn_fast', 4)
    assert len(calls) == 2


@pytest.mark.parametrize('step', [-1, 1])
def test_torch_correlation_equals_the_numba_kernel(step: int) -> None:
    rng = np.random.default_rng(5 + step)
    features = torch.nn.functional.normalize(torch.from_numpy(
        rng.standard_normal((2, 64, 6, 10)).astype(np.float32)), dim=1)
    by_numba = mccnn_fast.cosine_cost_volume(features[0], features[1], 4, step)
    by_torch = mccnn_fast.cosine_cost_volume_torch(features[0], features[1], 4, step)
    np.testing.assert_allclose(by_numba, by_torch, atol=1e-6)
    # hand check of one entry: (1 − cos) / 2
    x = 5
    cosine = float(features[0][:, 2, x] @ features[1][:, 2, x + 3 * step])
    assert by_numba[3, 2, x] == pytest.approx((1 - cosine) / 2, abs=1e-6)


def test_matches_the_mccnn_package_inference() -> None:
    run = pytest.importorskip('mc_cnn.run')
    weights = pytest.importorskip('mc_cnn.weights')
    left, right = shifted_pair(30, 40, 2, seed=6)
    depth = 6
    # The package's own pipeline: valid convolutions (no padding), cost = −cos, disparity
    # range [−(D − 1), 0] with left x paired with right x + d.
    theirs = run.run_mc_cnn_fast(
        left.astype(np.float32),
        right.astype(np.float32),
        -(depth - 1),
        0,
        str(weights.get_weights('fast', 'middlebury')),
        cost_volume_method='baseline',
    )
    ours = compute_cost_volume(left, right, 'mccnn_fast', depth)[:, 5:-5, 5:-5]
    theirs = np.stack([(1 + theirs[:, :, depth - 1 - d]) / 2 for d in range(depth)])
    known = np.isfinite(theirs)
    np.testing.assert_allclose(ours[known], theirs[known], atol=1e-5)


@pytest.mark.parametrize('device', ['gpu', 'cuda0', '', 3])
def test_bad_device(device: object) -> None:
    with pytest.raises(ConfigError, match='device'):
        mccnn_fast.MCCNNFastConfig(device=device)  # type: ignore[arg-type]


@pytest.mark.skipif(torch.cuda.is_available(), reason='CUDA is available here')
def test_cuda_without_cuda_is_a_config_error(pair: tuple[np.ndarray, np.ndarray]) -> None:
    with pytest.raises(ConfigError, match='CUDA is not available'):
        compute_cost_volume(*pair, 'mccnn_fast', 4, device='cuda')


@pytest.mark.filterwarnings('ignore:Detected pickle protocol')
def test_missing_or_foreign_weights(tmp_path: Path, pair: tuple[np.ndarray, np.ndarray]) -> None:
    with pytest.raises(ModelError, match='not found'):
        compute_cost_volume(*pair, 'mccnn_fast', 4, weights=str(tmp_path / 'none.pt'))
    foreign = tmp_path / 'foreign.pt'
    torch.save({'layer.weight': torch.zeros(3)}, foreign)
    with pytest.raises(ModelError, match='MC-CNN fast weights'):
        compute_cost_volume(*pair, 'mccnn_fast', 4, weights=str(foreign))
    garbage = tmp_path / 'garbage.pt'
    garbage.write_bytes(b'\x80\x04 not a torch file')
    with pytest.raises(ModelError, match='cannot read MC-CNN weights'):
        compute_cost_volume(*pair, 'mccnn_fast', 4, weights=str(garbage))
