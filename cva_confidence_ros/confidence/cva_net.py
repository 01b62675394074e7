"""``cva_net``: CVA-Net confidence from the left-reference cost volume (the learned method)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from cva_confidence_ros.confidence.base import (
    CONFIDENCE_METHODS,
    ConfidenceInputs,
    ConfidenceMethod,
)
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.model import (
    FoldedCVANet,
    default_weights_path,
    fold_batchnorm,
    load_weights,
    predict_confidence,
    predict_confidence_at,
    resolve_device,
)

__all__ = ['CVANetConfidence']


class CVANetConfidence(ConfidenceMethod):
    """CVA-Net applied to the whole cost volume; weights are loaded once, at construction.

    Args:
        matcher: The matcher whose cost volumes the weights were trained on.
        max_disparity: Cost-volume depth D the weights take.
        weights: Path of a weights file; None or '' = the shipped weights
            ``cvanet_<matcher>_d<D>.pt`` found by
            :func:`~cva_confidence_ros.model.default_weights_path`.
        device: ``'cpu'``, ``'cuda'`` or ``'auto'`` (CUDA when available).
        tile_budget_mb: Memory budget of one network tile, in megabytes.
        **_: Other generic options of the pipeline, ignored.

    Raises:
        ModelError: Weights missing, corrupt, or trained for another matcher or depth.
        ConfigError: Bad device or budget.
    """

    needs_right: ClassVar[bool] = False
    #: Network architecture of the weights (``model.ARCHITECTURES``); subclasses change it.
    arch: ClassVar[str] = 'cvanet'

    def __init__(
        self,
        matcher: str = 'census_bm',
        max_disparity: int = 64,
        weights: str | os.PathLike[str] | None = None,
        device: str = 'cpu',
        tile_budget_mb: float = 512.0,
        **_: Any,
    ) -> None:
        if tile_budget_mb <= 0:
            raise ConfigError(f'tile_budget_mb must be > 0; got {tile_budget_mb}')
        self.matcher = matcher
        self.max_disparity = int(max_disparity)
        self.device = resolve_device(device)
        self.tile_budget_mb = float(tile_budget_mb)
        path = (
            Path(weights)
            if weights
            else default_weights_path(matcher, self.max_disparity, self.arch)
        )
        net, self.meta = load_weights(
            path,
            matcher=matcher,
            max_disparity=self.max_disparity,
            device=self.device,
            arch=self.arch,
        )
        self.weights_path = path
        # Folding once here saves it on every frame.
        self._net = fold_batchnorm(net) if self.arch == 'cvanet' else net.fold_batchnorm()

    @property
    def net(self) -> FoldedCVANet | Any:
        """The loaded network, batch normalisations folded in (inference only)."""
        return self._net

    def _check(self, inputs: ConfidenceInputs) -> None:
        if inputs.max_disparity != self.max_disparity:
            raise InputError(
                f'{self.arch} weights {self.weights_path.name} take cost volumes of depth '
                f'D = {self.max_disparity}; got depth {inputs.max_disparity}'
            )
        if inputs.matcher and inputs.matcher != self.matcher:
            raise InputError(
                f'{self.arch} weights {self.weights_path.name} are for matcher {self.matcher!r}; '
                f'got a cost volume of {inputs.matcher!r}'
            )

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 confidence in (0, 1) for the left-reference cost volume.

        Raises:
            InputError: The volume's depth differs from the weights' D, or it comes from
                another matcher than the weights were trained for.
        """
        self._check(inputs)
        return predict_confidence(
            self._net, inputs.cost_volume, device=self.device, tile_budget_mb=self.tile_budget_mb
        )

    def confidence_at(
        self, inputs: ConfidenceInputs, ys: np.ndarray, xs: np.ndarray
    ) -> np.ndarray:
        """Confidence at the pixels (ys, xs) only, from 13×13×D extracts.

        Args:
            inputs: As for :meth:`__call__`.
            ys: (N,) integer rows.
            xs: (N,) integer columns.

        Returns:
            (N,) float32, equal to ``self(inputs)[ys, xs]`` (within 1e-5).

        Raises:
            InputError: As for :meth:`__call__`, or pixels outside the image.
        """
        self._check(inputs)
        return predict_confidence_at(self._net, inputs.cost_volume, ys, xs, device=self.device)


CONFIDENCE_METHODS.add('cva_net', CVANetConfidence)
