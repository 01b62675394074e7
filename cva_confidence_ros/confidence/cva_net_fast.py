"""``cva_net_fast``: CVA-Net-Fast confidence, the CPU-speed network on the same cost volume."""

from __future__ import annotations

from typing import ClassVar

from cva_confidence_ros.confidence.base import CONFIDENCE_METHODS
from cva_confidence_ros.confidence.cva_net import CVANetConfidence
from cva_confidence_ros.model.fast import CVANetFast

__all__ = ['CVANetFastConfidence']


class CVANetFastConfidence(CVANetConfidence):
    """CVA-Net-Fast applied to the whole cost volume (or to chosen pixels).

    Same options, checks and outputs as ``cva_net``
    (:class:`~cva_confidence_ros.confidence.cva_net.CVANetConfidence`); the shipped weights are
    ``cvanet_fast_<matcher>_d<D>.pt``, and ``weights`` must hold CVA-Net-Fast weights.
    """

    arch: ClassVar[str] = CVANetFast.arch


CONFIDENCE_METHODS.add('cva_net_fast', CVANetFastConfidence)
