"""Helpers shared by the matching tests: tiny textured pairs with a known disparity."""

from __future__ import annotations

import numpy as np


def shifted_pair(
    height: int, width: int, shift: int, seed: int = 0, colour: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Random-texture pair with left(y, x) == right(y, x − shift) wherever x ≥ shift."""
    rng = np.random.default_rng(seed)
    shape = (height, width + shift, 3) if colour else (height, width + shift)
    texture = rng.integers(0, 256, shape, dtype=np.uint8)
    left = np.ascontiguousarray(texture[:, :width])
    right = np.ascontiguousarray(texture[:, shift:shift + width])
    return left, right

