"""``cva_net``: CVA-Net confidence from the left-reference cost volume (the learned method).

By default the network runs on every pixel (the exact path). ``cva_stride``, ``cva_cascade``
and ``cva_cascade_fraction`` make it run on a subset and fill the rest
(:mod:`cva_confidence_ros.model.sparse`); ``cva_precision`` picks its arithmetic.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from torch import nn

from cva_confidence_ros.confidence.base import (
    CONFIDENCE_METHODS,
    GENERIC_OPTIONS,
    ConfidenceInputs,
    ConfidenceMethod,
    check_learned_options,
)
from cva_confidence_ros.errors import ConfigError, InputError, ModelError
from cva_confidence_ros.model import (
    SparseConfig,
    SparseEvaluator,
    default_weights_path,
    load_weights,
    resolve_device,
)
from cva_confidence_ros.model.inference import _check_pixels, _check_tile_budget

__all__ = ['CVANetConfidence']


class CVANetConfidence(ConfidenceMethod):
    """CVA-Net applied to the cost volume; weights are loaded once, at construction.

    The subclasses ``cva_net_lite`` and ``cva_net_fast`` run the lighter networks the same way,
    sparse evaluation included; ``weights`` must hold weights of the class's own architecture
    (``arch``: a CVA-Net-Lite file given to ``cva_net`` is refused, naming both).

    Args:
        matcher: The matcher whose cost volumes the weights were trained on.
        max_disparity: Cost-volume depth D the weights take.
        weights: Path of a weights file; None or '' = the shipped weights
            ``cvanet_<matcher>_d<D>.pt`` found by
            :func:`~cva_confidence_ros.model.default_weights_path`.
        device: ``'cpu'``, ``'cuda'`` or ``'auto'`` (CUDA when available).
        tile_budget_mb: Memory budget of one network tile, in megabytes.
        cva_stride: 1, 2, 4 or 8: run the network on every stride-th pixel per axis and fill
            the others by joint-bilateral interpolation (1 = every pixel).
        cva_cascade: ``none``, ``pkrn`` or ``lrd``: a cheap measure decides the pixels it is
            sure of first (``lrd`` makes the pipeline compute the right-reference volume).
        cva_cascade_fraction: Share (0, 1] of the pixels the cascade hands to the network.
        cva_precision: ``fp32``, ``bf16`` or ``fp16`` (CUDA only).
        cva_backend: ``torch``, or ``onnxruntime`` (the network exported to ONNX once and run
            by ONNX Runtime on the CPU).
        **_: Other generic options of the pipeline, ignored.

    Raises:
        ModelError: Weights missing, corrupt, or trained for another matcher or depth.
        ConfigError: Bad device, budget or sparse option (the message names the option), or
            an option that is neither a parameter nor a generic option.
    """

    needs_right: ClassVar[bool] = False
    probabilistic: ClassVar[bool] = True
    #: Network architecture of the weights (``model.ARCHITECTURES``); subclasses change it.
    arch: ClassVar[str] = 'cvanet'

    def __init__(
        self,
        matcher: str = 'census_bm',
        max_disparity: int = 64,
        weights: str | os.PathLike[str] | None = None,
        device: str = 'cpu',
        tile_budget_mb: float = 512.0,
        cva_stride: int = 1,
        cva_cascade: str = 'none',
        cva_cascade_fraction: float = 0.25,
        cva_precision: str = 'fp32',
        cva_backend: str = 'torch',
        **_: Any,
    ) -> None:
        # Only the pipeline's generic options may be ignored: a misspelt one (cva_strid=4)
        # would otherwise run the exact network without a word.
        unknown = set(_) - GENERIC_OPTIONS
        if unknown:
            raise ConfigError(
                f'unknown options {sorted(unknown)} for {type(self).__name__}; expected its '
                f'parameters or the generic {sorted(GENERIC_OPTIONS)}'
            )
        budget = _check_tile_budget(tile_budget_mb)
        self.sparse = SparseConfig(
            stride=cva_stride,
            cascade=cva_cascade,
            cascade_fraction=cva_cascade_fraction,
            precision=cva_precision,
        )
        # An instance attribute: the pipeline asks for the right view only for LRD.
        self.needs_right = self.sparse.cascade == 'lrd'  # type: ignore[misc]
        self.max_disparity = check_learned_options(matcher, weights, max_disparity)
        self.matcher = matcher
        self.device = resolve_device(device)
        self.tile_budget_mb = budget
        path = (
            Path(weights)
            if weights
            else default_weights_path(matcher, self.max_disparity, self.arch)
        )
        if weights and path.is_dir():
            # Path('') is the current folder, not "no path": say how to get the shipped ones.
            raise ModelError(
                f'weights {os.fspath(weights)!r} is a folder ({path.resolve()}), not a weights '
                f"file; None or '' selects the shipped weights"
            )
        net, self.meta = load_weights(
            path,
            matcher=matcher,
            max_disparity=self.max_disparity,
            device=self.device,
            arch=self.arch,
        )
        self.weights_path = path
        # Built once: BN folding and the operation counts of the tile shapes are not redone
        # on every frame.
        self._evaluator = SparseEvaluator(
            net,
            self.device,
            self.tile_budget_mb,
            precision=self.sparse.precision,
            backend=cva_backend,
        )
        self._cheap = (
            None
            if self.sparse.cascade == 'none'
            else CONFIDENCE_METHODS.get(self.sparse.cascade)()
        )

    @property
    def net(self) -> nn.Module:
        """The loaded network, batch normalisations folded in (inference only)."""
        return self._evaluator.net

    @property
    def evaluator(self) -> SparseEvaluator:
        """The network's evaluator (which way each tile ran: ``evaluator.path_counts``)."""
        return self._evaluator

    def _check(self, inputs: ConfidenceInputs) -> None:
        if not isinstance(inputs, ConfidenceInputs):
            # A bare cost volume failed with "'numpy.ndarray' object has no attribute".
            raise InputError(
                f'{type(self).__name__} takes a ConfidenceInputs (cost volume, disparity, '
                f'image); got {type(inputs).__name__}'
            )
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
        if self.needs_right and inputs.cost_volume_right is None:
            # Was LeftRightDifference's own refusal, naming a method the caller never chose.
            raise InputError(
                f"{type(self).__name__} with cva_cascade 'lrd' ranks the pixels by the "
                'left-right difference and needs the right-reference cost volume '
                "(ConfidenceInputs.cost_volume_right); got None (or take cva_cascade 'pkrn')"
            )

    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Return (H, W) float32 confidence in (0, 1) for the left-reference cost volume.

        Raises:
            InputError: The volume's depth differs from the weights' D, it comes from
                another matcher than the weights were trained for, or ``cva_cascade`` is
                ``lrd`` and the inputs lack the right-reference volume.
        """
        self._check(inputs)
        if self.sparse.exact:
            return self._evaluator(inputs.cost_volume)
        cheap = None if self._cheap is None else self._cheap(inputs)
        result = self._evaluator.confidence(
            inputs.cost_volume, inputs.image, inputs.disparity, self.sparse, cheap
        )
        return result.confidence

    def confidence_at(
        self, inputs: ConfidenceInputs, ys: np.ndarray, xs: np.ndarray
    ) -> np.ndarray:
        """Confidence at the pixels (ys, xs) only, from 13×13×D extracts.

        Args:
            inputs: As for :meth:`__call__`.
            ys: (N,) integer rows.
            xs: (N,) integer columns.

        Returns:
            (N,) float32, equal to ``self(inputs)[ys, xs]`` (within 1e-5). With sparse
            evaluation a pixel's value depends on its neighbours, so the whole map is computed
            and indexed.

        Raises:
            InputError: As for :meth:`__call__`, or pixels outside the image.
        """
        self._check(inputs)
        if not self.sparse.exact:
            # Checked here too: numpy would read a negative index from the other side.
            ys, xs = _check_pixels(ys, xs, inputs.cost_volume.shape[1:])
            return self(inputs)[ys, xs]
        return self._evaluator.at(inputs.cost_volume, ys, xs)


CONFIDENCE_METHODS.add('cva_net', CVANetConfidence)
