"""Confidence methods selected by name: hand-crafted measures and learned networks.

Every method module registers its methods in :data:`CONFIDENCE_METHODS` when it is imported;
adding a method is one new module and one import line at the end of this file.
"""

from __future__ import annotations

from cva_confidence_ros.confidence.base import (
    CONFIDENCE_METHODS,
    GENERIC_OPTIONS,
    ConfidenceFactory,
    ConfidenceInputs,
    ConfidenceMethod,
    compute_confidence,
    is_probabilistic,
)

__all__ = [
    'CONFIDENCE_METHODS',
    'GENERIC_OPTIONS',
    'ConfidenceFactory',
    'ConfidenceInputs',
    'ConfidenceMethod',
    'compute_confidence',
    'is_probabilistic',
]

# Method modules, imported for their registrations: add one line per module, keep them sorted.
from cva_confidence_ros.confidence import (  # noqa: E402
    baselines,  # noqa: F401  (ccnn, lfn, lgc_net)
    cva_net,  # noqa: F401  (cva_net)
    cva_net_fast,  # noqa: F401  (cva_net_fast)
    cva_net_lite,  # noqa: F401  (cva_net_lite)
    handcrafted,  # noqa: F401  (pkrn, mlm, lrd, lrc, score)
)
