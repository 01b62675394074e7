"""Review 30: the extracts path of the sparse evaluator keeps to its memory budget."""

from __future__ import annotations

import numpy as np
import torch

from cva_confidence_ros.model import CVANet, SparseEvaluator


def test_extract_batches_keep_to_the_memory_budget() -> None:
    # 512 extracts ran at once whatever tile_budget_mb said: at D = 128 and 64 MB the
    # extracts path took 0.8 GB where the tile path kept to 0.2 GB.
    torch.manual_seed(0)
    net = CVANet(16)
    rng = np.random.default_rng(0)
    volume = rng.random((16, 20, 30), dtype=np.float32)
    ys, xs = np.nonzero(np.ones((20, 30), bool))
    whole = SparseEvaluator(net, tile_budget_mb=1e4)
    tight = SparseEvaluator(net, tile_budget_mb=20)
    assert whole.extract_batch == 512
    assert 1 <= tight.extract_batch < 512
    # (the per-extract count of tile_shape: 4 bytes × 3 live copies × 169 pixels × 32 · D)
    per_extract = 4 * 3 * 169 * 32 * 16
    assert tight.extract_batch * per_extract <= 20e6 < (tight.extract_batch + 1) * per_extract
    seen: list[int] = []

    def record(_: object, args: tuple[torch.Tensor, ...]) -> None:
        if args[0].device.type != 'meta':  # (the flop counter runs a deep copy on 'meta')
            seen.append(args[0].shape[0])

    hook = tight.net.register_forward_pre_hook(record)
    try:
        values = tight.at(volume, ys, xs)
    finally:
        hook.remove()
    assert max(seen) == tight.extract_batch and sum(seen) == ys.size
    np.testing.assert_allclose(values, whole.at(volume, ys, xs), atol=1e-5)
