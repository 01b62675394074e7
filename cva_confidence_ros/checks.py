"""Type tests shared by the option and argument checks of the whole package.

``bool`` is a subclass of ``int`` in Python, so ``isinstance(True, int)`` holds; an option
that takes a count, a depth or a size never means ``True``. Numpy scalars count as numbers.
"""

from __future__ import annotations

from numbers import Real

import numpy as np

__all__ = ['is_int', 'is_real']


def is_int(value: object) -> bool:
    """A Python or numpy integer, ``bool`` excluded."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_real(value: object) -> bool:
    """A real scalar (Python or numpy, ints included), ``bool`` excluded; NaN and ±inf are
    real here, the caller checks finiteness where it matters."""
    return isinstance(value, (Real, np.integer)) and not isinstance(value, (bool, np.bool_))
