"""Training samples: extracts, dense crops, sampling order, labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.model import CVANet
from cva_confidence_ros.training.data import (
    PreparedScene,
    dense_crops,
    epoch_order,
    flip_draws,
    gather_crops,
    gather_extracts,
    prepare_scene,
    sample_index,
    validation_subset,
)

DEPTH = 16


def _scene(seed: int, height: int = 18, width: int = 21) -> PreparedScene:
    rng = np.random.default_rng(seed)
    volume = rng.random((DEPTH, height + 12, width + 12)).astype(np.float16)
    volume[:, :6] = volume[:, -6:] = 0
    volume[:, :, :6] = volume[:, :, -6:] = 0
    labelled = rng.random((height, width)) < 0.6
    correct = rng.random((height, width)) < 0.7
    return PreparedScene(f'toy/{seed}', 1, torch.from_numpy(volume), labelled, correct)


@pytest.fixture(scope='module')
def scenes() -> list[PreparedScene]:
    return [_scene(0), _scene(1, 15, 25)]


def test_sample_index(scenes):
    index = sample_index(scenes)
    assert len(index) == sum(s.n_labelled for s in scenes)
    assert index.fraction_wrong == pytest.approx(sum(s.n_wrong for s in scenes) / len(index))
    for n in (0, len(index) - 1):
        scene = scenes[index.scene[n]]
        assert scene.labelled[index.ys[n], index.xs[n]]
        assert index.target[n] == scene.correct[index.ys[n], index.xs[n]]


def test_epoch_order_is_seeded_and_covers_all():
    first = epoch_order(10, 25, seed=3, epoch=0)
    np.testing.assert_array_equal(first, epoch_order(10, 25, seed=3, epoch=0))
    assert not np.array_equal(first, epoch_order(10, 25, seed=3, epoch=1))
    assert sorted(first[:10]) == list(range(10))  # every sample once before repeats
    assert len(first) == 25


def test_extracts_are_centred_windows(scenes):
    index = sample_index(scenes)
    chosen = np.array([0, 5, len(index) - 1, 3])
    volumes, targets = gather_extracts(scenes, index, chosen)
    assert volumes.shape == (4, 1, DEPTH, 13, 13) and volumes.dtype == torch.float32
    for row, n in enumerate(chosen):
        y, x = index.ys[n], index.xs[n]
        # Output pixel (y, x) sees padded rows y … y + 12: the window centred on it.
        expected = scenes[index.scene[n]].volume[:, y : y + 13, x : x + 13].float()
        torch.testing.assert_close(volumes[row, 0], expected)
        assert targets[row] == index.target[n]


def test_dense_crops_count_labels(scenes):
    index = sample_index(scenes)
    crops = dense_crops(scenes, index, n_samples=300, crop_size=8, seed=0, epoch=0)
    assert crops.n_labelled.sum() >= 300
    for row in range(len(crops.scene)):
        scene = scenes[crops.scene[row]]
        y0, x0 = crops.y0[row], crops.x0[row]
        assert 0 <= y0 <= scene.shape[0] - 8 and 0 <= x0 <= scene.shape[1] - 8
        assert crops.n_labelled[row] == scene.labelled[y0 : y0 + 8, x0 : x0 + 8].sum()
    volumes, targets, mask = gather_crops(scenes, crops, np.array([0, 1]), 8)
    assert volumes.shape == (2, 1, DEPTH, 20, 20)
    assert targets.shape == mask.shape == (2, 8, 8)
    assert int(mask[0].sum()) == crops.n_labelled[0]


def test_crop_outputs_equal_extract_outputs(scenes):
    """A dense crop trains the same per-pixel function as the sparse extracts."""
    torch.manual_seed(0)
    net = CVANet(DEPTH).eval()
    index = sample_index(scenes)
    crops = dense_crops(scenes, index, n_samples=1, crop_size=6, seed=1, epoch=0)
    volumes, _, _ = gather_crops(scenes, crops, np.array([0]), 6)
    scene_number, y0, x0 = crops.scene[0], crops.y0[0], crops.x0[0]
    with torch.no_grad():
        dense = net.forward_logits(volumes)[0]
        for i, j in ((0, 0), (5, 5), (2, 4)):
            window = scenes[scene_number].volume[:, y0 + i : y0 + i + 13, x0 + j : x0 + j + 13]
            single = net.forward_logits(window.float()[None, None])[0, 0, 0]
            torch.testing.assert_close(dense[i, j], single, atol=1e-5, rtol=1e-5)


def _upside_down(scene: PreparedScene) -> PreparedScene:
    return PreparedScene(
        scene.name,
        scene.factor,
        scene.volume.flip(1),
        scene.labelled[::-1].copy(),
        scene.correct[::-1].copy(),
    )


def test_flipped_crops_are_crops_of_the_flipped_scene(scenes):
    index = sample_index(scenes)
    crops = dense_crops(scenes, index, n_samples=200, crop_size=8, seed=0, epoch=0)
    rows = np.arange(min(6, len(crops.scene)))
    flip = np.array([True, False] * 3)[: rows.size]
    volumes, targets, mask = gather_crops(scenes, crops, rows, 8, flip)
    plain, plain_targets, plain_mask = gather_crops(scenes, crops, rows, 8)
    for row in rows:
        if not flip[row]:
            torch.testing.assert_close(volumes[row], plain[row])
            continue
        scene = scenes[crops.scene[row]]
        upside = _upside_down(scene)
        # The crop at rows y0 … y0 + 7 of the scene is at rows H − y0 − 8 … of the flipped one.
        y0, x0 = scene.shape[0] - 8 - crops.y0[row], crops.x0[row]
        expected = upside.volume[:, y0 : y0 + 20, x0 : x0 + 20].float()
        torch.testing.assert_close(volumes[row, 0], expected)
        np.testing.assert_array_equal(targets[row], upside.correct[y0 : y0 + 8, x0 : x0 + 8])
        np.testing.assert_array_equal(mask[row], upside.labelled[y0 : y0 + 8, x0 : x0 + 8])
        assert int(mask[row].sum()) == int(plain_mask[row].sum())


def test_flipped_extracts_are_upside_down_windows(scenes):
    index = sample_index(scenes)
    chosen = np.array([0, 7, 11])
    flip = np.array([True, False, True])
    volumes, _ = gather_extracts(scenes, index, chosen, flip)
    plain, _ = gather_extracts(scenes, index, chosen)
    torch.testing.assert_close(volumes[0], plain[0].flip(-2))
    torch.testing.assert_close(volumes[1], plain[1])
    torch.testing.assert_close(volumes[2], plain[2].flip(-2))
    assert not torch.equal(volumes[0], plain[0])


def test_flip_draws_are_seeded_and_off_by_default():
    assert not flip_draws(50, seed=0, epoch=0, enabled=False).any()
    drawn = flip_draws(1000, seed=0, epoch=0, enabled=True)
    np.testing.assert_array_equal(drawn, flip_draws(1000, seed=0, epoch=0, enabled=True))
    assert not np.array_equal(drawn, flip_draws(1000, seed=0, epoch=1, enabled=True))
    assert 400 < drawn.sum() < 600


def test_census_bm_volume_of_upside_down_pair_is_upside_down():
    """Why the vertical flip is a valid augmentation: it commutes with the matcher."""
    from cva_confidence_ros.matching import compute_cost_volume

    rng = np.random.default_rng(4)
    left = rng.integers(0, 256, size=(24, 40), dtype=np.uint8)
    right = np.roll(left, -3, axis=1)
    volume = compute_cost_volume(left, right, 'census_bm', DEPTH)
    upside = compute_cost_volume(left[::-1].copy(), right[::-1].copy(), 'census_bm', DEPTH)
    np.testing.assert_allclose(upside, volume[:, ::-1], atol=1e-6)


def test_validation_subset_is_fixed(scenes):
    first = validation_subset(scenes, 40, seed=5)
    again = validation_subset(scenes, 40, seed=5)
    assert sum(ys.size for ys, _ in first) == 40
    for (ys, xs), (ys2, xs2), scene in zip(first, again, scenes, strict=True):
        np.testing.assert_array_equal(ys, ys2)
        np.testing.assert_array_equal(xs, xs2)
        assert scene.labelled[ys, xs].all()


def test_prepare_scene_labels_by_kitti_criterion():
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity

    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, size=(20, 48), dtype=np.uint8)
    shift = 5
    right = np.roll(left, -shift, axis=1)
    truth = np.full((20, 48), float(shift), np.float32)
    truth[:, :4] = np.nan
    truth[0, 10] = shift + 10.0  # a wrong ground truth makes that pixel's WTA disparity wrong
    sample = StereoSample('toy', 'shift', left, right, truth)
    scene = prepare_scene(sample, 'census_bm', DEPTH)
    volume = compute_cost_volume(left, right, 'census_bm', DEPTH)
    estimate = wta_disparity(volume)
    assert scene.factor == 1 and scene.volume.dtype == torch.float16
    assert scene.volume.shape == (DEPTH, 32, 60)
    np.testing.assert_array_equal(scene.labelled, np.isfinite(truth))
    expected = (np.abs(estimate - truth) < 3) & np.isfinite(truth)
    np.testing.assert_array_equal(scene.correct, expected)
    assert not scene.correct[0, 10]
    np.testing.assert_allclose(scene.unpadded_volume(), volume, atol=1e-3)


@pytest.mark.parametrize(('items', 'world'), [(1, 4), (5, 4), (8, 4), (7, 1)])
def test_process_shares_are_equal_and_complete(items, world):
    from cva_confidence_ros.training.trainer import _Dist, _share

    shares = [_share(np.arange(items), _Dist(r, world, torch.device('cpu'))) for r in range(world)]
    assert len({len(s) for s in shares}) == 1  # DDP needs the same number of steps everywhere
    assert set(np.concatenate(shares)) == set(range(items))
