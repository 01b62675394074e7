"""Fixtures shared by the test folders."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
import resource
import signal
from types import ModuleType

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
def ort() -> ModuleType:
    """``onnxruntime``, or the test is skipped where ``onnx`` or it is not installed."""
    pytest.importorskip('onnx')
    return pytest.importorskip('onnxruntime')


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


@contextmanager
def _file_size_limit(limit: int) -> Iterator[None]:
    old_limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, old_limit[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old_limit)
        signal.signal(signal.SIGXFSZ, old_handler)


@pytest.fixture
def file_size_limit() -> Callable[[int], AbstractContextManager[None]]:
    """``with file_size_limit(n):`` files may grow to ``n`` bytes only: a write past it fails
    (EFBIG), as on a full disk."""
    return _file_size_limit
