"""Review 31: the distillation loss's inputs, and point clouds at the edges of float32 (the cut
at a threshold, points beyond float32, colours packed as integers)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import filter_cloud, make_cloud, pack_rgb, unpack_rgb
from cva_confidence_ros.training.distill import distillation_loss

LOGITS = torch.tensor([0.5, -1.0, 2.0])
LABELS = torch.tensor([1.0, 0.0, 0.0])


@pytest.mark.parametrize('labels', [LABELS.bool(), LABELS.long(), LABELS.to(torch.uint8)])
def test_distillation_loss_takes_bool_and_integer_labels(labels: torch.Tensor) -> None:
    # A bool label map (1 = correct) crashed inside torch ("Subtraction ... with two bool
    # tensors is not supported"), an integer one with "result type Float can't be cast".
    expected = float(distillation_loss(LOGITS, LABELS, None, 0.0))
    assert float(distillation_loss(LOGITS, labels, None, 0.0)) == pytest.approx(expected)
    teacher = torch.tensor([0.0, 1.0, -1.0])
    mixed = float(distillation_loss(LOGITS, LABELS, teacher, 0.4))
    assert float(distillation_loss(LOGITS, labels, teacher, 0.4)) == pytest.approx(mixed)


@pytest.mark.parametrize(
    ('logits', 'targets', 'teacher', 'match'),
    [
        # No outputs but three labels: was a silent 0.
        (torch.zeros(0), torch.zeros(3), None, r'targets .* logits \(0,\); got \(3,\)'),
        (torch.zeros(0), torch.zeros(0), torch.zeros(3), r'teacher logits .* got \(3,\)'),
        # Teacher logits of (B, H, W) against flattened student outputs: was torch's
        # "Target size ... must be the same as input size", naming neither tensor.
        (LOGITS, LABELS, torch.zeros(3, 1), r'teacher logits .* \(3,\); got \(3, 1\)'),
        (LOGITS, LABELS[:2], None, r'targets .* \(3,\); got \(2,\)'),
    ],
)
def test_distillation_loss_refuses_other_shapes(
    logits: torch.Tensor, targets: torch.Tensor, teacher: torch.Tensor | None, match: str
) -> None:
    with pytest.raises(InputError, match=match):
        distillation_loss(logits, targets, teacher, 0.5 if teacher is not None else 0.0)


@pytest.mark.parametrize('weight', ['0.5', None])
def test_distillation_loss_refuses_a_weight_that_is_no_number(weight: object) -> None:
    # Was a TypeError from the comparison ("'<=' not supported between ...").
    with pytest.raises(ConfigError, match=r'distill weight must be in \[0, 1\]'):
        distillation_loss(LOGITS, LABELS, torch.zeros(3), weight)  # type: ignore[arg-type]


def _cloud(confidence: list[float]) -> np.ndarray:
    points = np.zeros((1, len(confidence), 3), np.float32)
    points[..., 2] = 1.0
    colours = np.zeros((1, len(confidence)), np.float32)
    return make_cloud(points, colours, confidence=np.array([confidence]))


def test_filter_cloud_keeps_a_confidence_equal_to_the_threshold() -> None:
    # The cloud holds float32(0.7) = 0.69999999; a np.float64 threshold of 0.7 (np.quantile's,
    # say) compared in float64 and dropped it, a Python float 0.7 kept it.
    cloud = _cloud([0.7, 0.3, 1.0, 0.69])
    for threshold in (0.7, np.float64(0.7), np.float32(0.7)):
        kept = filter_cloud(cloud, threshold, organized=False)
        assert kept['confidence'].tolist() == pytest.approx([0.7, 1.0]), type(threshold)
        organised = filter_cloud(cloud, threshold)
        assert np.isfinite(organised['z']).tolist() == [[True, False, True, False]]


def test_filter_cloud_threshold_in_float16_and_float64_fields() -> None:
    for code in ('<f2', '>f4', '<f8'):
        cloud = np.zeros(2, [('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('confidence', code)])
        cloud['confidence'] = [0.7, 0.6]
        for threshold in (0.7, np.float64(0.7), np.float32(0.7)):
            assert len(filter_cloud(cloud, threshold, organized=False)) == 1, (code, threshold)


def test_make_cloud_refuses_float64_points_beyond_float32() -> None:
    # A finite float64 point of 1e39 was stored as x = inf and kept as a valid point.
    points = np.zeros((1, 2, 3))
    points[..., 2] = 1.0
    points[0, 0, 0] = 1e39
    colours = np.zeros((1, 2), np.float32)
    with pytest.raises(InputError, match=r'fit float32.*1 do not.*1e\+39'):
        make_cloud(points, colours, organized=False)
    points[0, 0, 0] = np.nan  # a dropped point may hold anything
    assert make_cloud(points, colours, organized=False).shape == (1,)
    points[0, 0, 0] = float(np.finfo(np.float32).max)  # the largest float32 itself fits
    assert np.isfinite(make_cloud(points, colours)['x']).all()


def test_unpack_rgb_reads_integer_colours_as_bits() -> None:
    # PointCloud2 rgb / rgba fields of datatype UINT32 decode as uint32: the number was
    # converted to float32 first, so 0x00FF0102 came back as (127, 1, 2).
    expected = [[255, 1, 2], [0, 128, 255]]
    packed = np.array([0x00FF0102, 0xFF0080FF], np.uint32)  # the second with alpha 0xFF
    assert unpack_rgb(packed).tolist() == expected
    assert unpack_rgb(packed.astype(np.int64)).tolist() == expected
    image = np.array([expected], np.uint8)
    assert unpack_rgb(pack_rgb(image)).tolist() == [expected]
    assert unpack_rgb(pack_rgb(image).view(np.uint32)).tolist() == [expected]
    with pytest.raises(InputError, match='dtype bool'):
        unpack_rgb(np.array([True]))
