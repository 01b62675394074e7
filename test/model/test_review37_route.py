"""Review 37: the sparse evaluator's choice of route, and its counters under threads."""

from __future__ import annotations

import threading

import numpy as np
import torch

from cva_confidence_ros.model import CVANet, CVANetFast, CVANetLite, SparseEvaluator
from cva_confidence_ros.model.sparse import _grid_axis
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline


def _pair(height: int = 48, width: int = 96, shift: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    texture = rng.integers(0, 256, (height, width + shift), dtype=np.uint8)
    return np.ascontiguousarray(texture[:, shift:]), np.ascontiguousarray(texture[:, :width])


def test_warm_up_in_a_thread_keeps_the_counts_of_a_frame_processed_meanwhile() -> None:
    # The node warms up in a thread while its first frame arrives: the warm-up saved the
    # evaluator's counters, ran, and put them back, dropping the frame's counts (and its
    # progress reports, switched off for the warm-up's duration).
    pipeline = StereoPipeline(PipelineConfig(device='cpu', confidence_method='cva_net_fast'))
    evaluator = pipeline._method.evaluator  # type: ignore[attr-defined]
    reports: list[tuple[int, int]] = []
    evaluator.progress = lambda done, total: reports.append((done, total))
    started, processed = threading.Event(), threading.Event()
    window = pipeline._warm_up_window

    def paused_window(height: int, width: int) -> tuple[int, int] | None:
        # Called inside the warm-up, before its frame: hold it until the real frame is done.
        started.set()
        processed.wait(60)
        return window(height, width)

    pipeline._warm_up_window = paused_window  # type: ignore[method-assign]
    warm = threading.Thread(target=pipeline.warm_up)
    warm.start()
    try:
        assert started.wait(60)
        pipeline.process(*_pair())
        counts, flops = dict(evaluator.path_counts), evaluator.flops_done
        assert sum(counts.values()) >= 1 and flops > 0 and reports
    finally:
        processed.set()
        warm.join(60)
    assert not warm.is_alive()
    assert evaluator.path_counts == counts and evaluator.flops_done == flops
    assert len(reports) == sum(counts.values())  # none from the warm-up's own frame
    assert evaluator.progress is not None



def _grid(height: int, width: int, stride: int) -> np.ndarray:
    mask = np.zeros((height, width), dtype=bool)
    mask[np.ix_(_grid_axis(height, stride), _grid_axis(width, stride))] = True
    return mask


def test_fast_network_fuses_densely_at_stride_8() -> None:
    # By counted operations alone, extracts looked cheaper for CVA-Net-Fast at stride 8
    # (7.4 against 9.3 GFLOP at 320×240) but ran 1.6× slower (115 against 72 ms): their
    # gathering of 13×13×D values per pixel was not counted.
    torch.manual_seed(0)
    evaluator = SparseEvaluator(CVANetFast(max_disparity=64))
    mask = _grid(120, 160, 8)
    volume = np.random.default_rng(0).random((64, 120, 160), dtype=np.float32)
    fused = evaluator(volume, mask)
    assert evaluator.path_counts == {'tile': 0, 'fused': 1, 'extracts': 0}
    extracts = SparseEvaluator(evaluator.net, path='extracts')(volume, mask)
    np.testing.assert_allclose(fused[mask], extracts[mask], atol=1e-5)
    # flops_done stays the operations run, without the gathering's weight.
    assert evaluator.flops_done == evaluator._costs(120, 160, int(mask.sum()))['fused']
    # The heavier networks keep their ways: extracts at stride 8, dense fusion at stride 4.
    for net in (CVANet(max_disparity=64), CVANetLite(max_disparity=64)):
        heavy = SparseEvaluator(net)
        for stride, way in ((8, 'extracts'), (4, 'fused')):
            assert heavy._choose(120, 132, int(_grid(120, 132, stride).sum())) == way
