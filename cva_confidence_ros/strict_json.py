"""JSON that strict readers accept: no ``NaN`` or ``Infinity``, numpy scalars as plain numbers.

``json.dumps`` writes a NaN or infinite float as ``NaN`` / ``Infinity`` unless told
``allow_nan=False``. Neither is a JSON token: jq, JavaScript's ``JSON.parse`` and Go's
``encoding/json`` refuse the whole file. Every JSON file of the package (``report.json``, the
benchmark and node-benchmark records, ``history.json``, the model cards, ``calibration.json``,
the demo's summary) goes through :func:`dumps`, which writes such a value as ``null``: unknown,
as a metric of a frame without ground truth is.
"""

from __future__ import annotations

from collections.abc import Mapping
import json
import math
from typing import Any

import numpy as np

__all__ = ['dumps', 'json_ready']


def json_ready(value: Any) -> Any:
    """``value`` with every NaN or infinite float as None, inside dicts, lists and tuples too;
    numpy scalars and arrays as Python numbers and lists (``json.dumps`` refuses
    ``np.float32`` and ``np.int64``)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {key: json_ready(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(item) for item in value]
    return value


def dumps(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`json_ready` ``(value)``: strict JSON, NaN and infinity as
    ``null``. ``kwargs`` go to ``json.dumps`` (``indent``, ``sort_keys``)."""
    return json.dumps(json_ready(value), allow_nan=False, **kwargs)
