"""Evaluation of confidence methods with the paper's ROC/AUC protocol (``cva-evaluate``).

Reusable pieces: :func:`evaluate_scene` (one scene × matcher × methods → records, optional
PNGs), :func:`format_table` (records → Table-1 Markdown), :func:`write_records` /
:func:`read_records` (JSON).
"""

from __future__ import annotations

from cva_confidence_ros.evaluation.records import (
    RECORD_KEYS,
    EvalRecord,
    format_table,
    read_records,
    write_records,
)
from cva_confidence_ros.evaluation.scene import (
    ScoredMethod,
    confidence_at,
    evaluate_scene,
    overlay_threshold,
    score_confidence,
    select_pixels,
)

__all__ = [
    'RECORD_KEYS',
    'EvalRecord',
    'ScoredMethod',
    'confidence_at',
    'evaluate_scene',
    'format_table',
    'overlay_threshold',
    'read_records',
    'score_confidence',
    'select_pixels',
    'write_records',
]
