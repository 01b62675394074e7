"""Fixtures shared by the test folders."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Run the test with one torch thread (steady timings and results on a shared machine)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def slanted_pair() -> tuple[np.ndarray, np.ndarray]:
    """A 120×96 pair of random texture on a slanted plane: the disparity grows with the row
    from 3 to 11 px (so a region of rows has a disparity of its own)."""
    height, width = 96, 120
    rng = np.random.default_rng(5)
    texture = rng.integers(0, 256, (height, width + 16), dtype=np.uint8)
    left = texture[:, :width].copy()
    right = np.empty_like(left)
    for y in range(height):
        shift = 3 + (8 * y) // height
        right[y] = texture[y, shift : shift + width]
    return left, right
