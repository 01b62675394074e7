"""What every training test shares."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _restore_threads() -> Iterator[None]:
    """``--threads 1`` changes process-wide settings; give the other tests theirs back."""
    import numba

    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    yield
    numba.set_num_threads(numba_threads)
    torch.set_num_threads(threads)
