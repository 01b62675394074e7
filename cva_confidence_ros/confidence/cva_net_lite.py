"""``cva_net_lite``: CVA-Net-Lite confidence, the distilled light network on the same volume."""

from __future__ import annotations

from typing import ClassVar

from cva_confidence_ros.confidence.base import CONFIDENCE_METHODS
from cva_confidence_ros.confidence.cva_net import CVANetConfidence
from cva_confidence_ros.model.lite import CVANetLite

__all__ = ['CVANetLiteConfidence']


class CVANetLiteConfidence(CVANetConfidence):
    """CVA-Net-Lite applied to the whole cost volume (or to chosen pixels).

    Same options, checks and outputs as ``cva_net``
    (:class:`~cva_confidence_ros.confidence.cva_net.CVANetConfidence`); the shipped weights are
    ``cvanet_lite_<matcher>_d<D>.pt``, and ``weights`` must hold CVA-Net-Lite weights.
    """

    arch: ClassVar[str] = CVANetLite.arch


CONFIDENCE_METHODS.add('cva_net_lite', CVANetLiteConfidence)
