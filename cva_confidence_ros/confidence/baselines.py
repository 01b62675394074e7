"""``ccnn``, ``lfn``, ``lgc_net``: the learned baselines that read the disparity map (+ image).

They look at ``ConfidenceInputs.disparity`` (the winner-takes-all disparity; NaN = invalid is
filled with 0 before the network's ÷ D) and ``ConfidenceInputs.image`` (grey or RGB, used as
grey), never at the cost volume; the volume's depth is still checked against the weights' D,
because the disparity range the network learned is [0, D).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from cva_confidence_ros.confidence.base import (
    CONFIDENCE_METHODS,
    GENERIC_OPTIONS,
    ConfidenceInputs,
    ConfidenceMethod,
    check_learned_options,
)
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import default_weights_path, load_weights, resolve_device
from cva_confidence_ros.model.baselines import predict_disparity_confidence

__all__ = ['BASELINE_METHODS', 'CCNNConfidence', 'LFNConfidence', 'LGCNetConfidence']


class _DisparityNetConfidence(ConfidenceMethod):
    """A baseline network applied to the whole disparity map; weights loaded at construction.

    Args:
        matcher: The matcher whose disparity maps the weights were trained on.
        max_disparity: D the weights were trained for.
        weights: Weights file; None or '' = the shipped ``<arch>_<matcher>_d<D>.pt``.
        device: ``'cpu'``, ``'cuda'`` or ``'auto'``.
        **_: Other generic options of the pipeline (``tile_budget_mb``), ignored: these
            networks run on the whole image in one pass.

    Raises:
        ModelError: Weights missing, corrupt, of another architecture, or for another matcher
            or D.
        ConfigError: ``matcher`` not a non-empty str, ``weights`` not a path,
            ``max_disparity`` not an integer ≥ 1, a bad device, or an option that is neither
            a parameter nor a generic option.
    """

    arch: ClassVar[str] = ''
    method: ClassVar[str] = ''
    needs_right: ClassVar[bool] = False
    probabilistic: ClassVar[bool] = True

    def __init__(
        self,
        matcher: str = 'census_bm',
        max_disparity: int = 64,
        weights: str | os.PathLike[str] | None = None,
        device: str = 'cpu',
        **_: Any,
    ) -> None:
        # Only the pipeline's generic options may be ignored: a misspelt one (weigths=...)
        # would otherwise load the shipped weights without a word.
        unknown = set(_) - GENERIC_OPTIONS
        if unknown:
            raise ConfigError(
                f'unknown options {sorted(unknown)} for {type(self).__name__}; expected its '
                f'parameters or the generic {sorted(GENERIC_OPTIONS)}'
            )
        self.max_disparity = check_learned_options(matcher, weights, max_disparity)
        self.matcher = matcher
        self.device = resolve_device(device)
        path = (
            Path(weights) if weights else default_weights_path(matcher, self.max_disparity,
                                                               self.arch)
        )
        self.net, self.meta = load_weights(
            path, matcher=matcher, max_disparity=self.max_disparity, device=self.device,
            arch=self.arch,
        )
        self.weights_path = path

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 confidence in (0, 1) of the left WTA disparity.

        Raises:
            InputError: ``inputs`` not a :class:`ConfidenceInputs`, the volume's depth differs
                from the weights' D, or the inputs come from another matcher than the weights
                were trained for.
        """
        if not isinstance(inputs, ConfidenceInputs):
            # A bare array failed with "'numpy.ndarray' object has no attribute".
            raise InputError(
                f'{type(self).__name__} takes a ConfidenceInputs (cost volume, disparity, '
                f'image); got {type(inputs).__name__}'
            )
        if inputs.max_disparity != self.max_disparity:
            raise InputError(
                f'{self.method} weights {self.weights_path.name} are for D = '
                f'{self.max_disparity}; got a cost volume of depth {inputs.max_disparity}'
            )
        if inputs.matcher and inputs.matcher != self.matcher:
            raise InputError(
                f'{self.method} weights {self.weights_path.name} are for matcher '
                f'{self.matcher!r}; got inputs of {inputs.matcher!r}'
            )
        return predict_disparity_confidence(self.net, inputs.disparity, inputs.image, self.device)


class CCNNConfidence(_DisparityNetConfidence):
    """CCNN (Poggi & Mattoccia 2016) on the disparity map."""

    arch = 'ccnn'
    method = 'ccnn'


class LFNConfidence(_DisparityNetConfidence):
    """LFN (Fu et al. 2017) on the disparity map and the left image."""

    arch = 'lfn'
    method = 'lfn'


class LGCNetConfidence(_DisparityNetConfidence):
    """LGC-Net (Tosi et al. 2018): CCNN + ConfNet + fusion, on disparity map and image."""

    arch = 'lgcnet'
    method = 'lgc_net'


#: Registered method name → class.
BASELINE_METHODS: dict[str, type[_DisparityNetConfidence]] = {
    cls.method: cls for cls in (CCNNConfidence, LFNConfidence, LGCNetConfidence)
}
for _name, _cls in BASELINE_METHODS.items():
    CONFIDENCE_METHODS.add(_name, _cls)
