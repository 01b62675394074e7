"""Inputs, base class and registry shared by every confidence method.

A method is registered under a name as a *factory* ``(**options) -> ConfidenceMethod``. The
pipeline calls every factory with the same generic options (:data:`GENERIC_OPTIONS`); a method
ignores those it has no use for, so one call site serves hand-crafted and learned methods.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, fields, is_dataclass
import inspect
import os
from typing import Any, ClassVar

import numpy as np

from cva_confidence_ros.checks import is_int
from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.registry import Registry

__all__ = [
    'CONFIDENCE_METHODS',
    'GENERIC_OPTIONS',
    'ConfidenceFactory',
    'ConfidenceInputs',
    'ConfidenceMethod',
    'check_learned_options',
    'compute_confidence',
    'is_probabilistic',
]

#: Options the pipeline passes to every factory; methods that do not use them ignore them.
GENERIC_OPTIONS = frozenset(
    {
        'matcher',
        'max_disparity',
        'weights',
        'device',
        'tile_budget_mb',
        # Sparse evaluation and precision of a cost-volume network (cva_net and its kin).
        'cva_stride',
        'cva_cascade',
        'cva_cascade_fraction',
        'cva_precision',
        'cva_backend',
    }
)


#: dtype kinds accepted for cost volumes and disparities: float, signed and unsigned int.
_REAL_KINDS = 'fiu'
#: Slack around [0, 1] for costs, so that float rounding in a matcher is not an error.
_COST_TOLERANCE = 1e-4
#: The bounds as float32 holds them: 1 + 1e-4 is 1.00010001659 there, above the float64 sum,
#: so a float32 cost at the bound (or a float64 one, once cast) was refused.
_COST_LOW = np.float32(-_COST_TOLERANCE)
_COST_HIGH = np.float32(1.0 + _COST_TOLERANCE)


def _as_volume(name: str, volume: Any) -> np.ndarray:
    if not isinstance(volume, np.ndarray):
        raise InputError(f'{name} must be a numpy array; got {type(volume).__name__}')
    if volume.dtype.kind not in _REAL_KINDS:
        raise InputError(f'{name} must hold real numbers (float or int); got dtype {volume.dtype}')
    if volume.ndim != 3 or 0 in volume.shape:
        raise InputError(f'{name} must be a non-empty (D, H, W) array; got shape {volume.shape}')
    # Two reductions per frame; NaN propagates into both, and ±inf falls outside the range.
    # Taken before the cast, which keeps the order: the extremes as float32 are the float32
    # volume's, and a float64 cost of 1e300 is reported as such, not as float32's inf (nor
    # with its overflow warning).
    low, high = volume.min(), volume.max()
    with np.errstate(over='ignore'):
        inside = _COST_LOW <= np.float32(low) and np.float32(high) <= _COST_HIGH
    if not inside:
        # min and max are NaN as soon as one entry is: '[nan, nan]' told nothing about the
        # others. The hint says how a volume of another matcher goes in (class docstring).
        nans = int(np.count_nonzero(np.isnan(volume))) if volume.dtype.kind == 'f' else 0
        if nans:
            got = f'{nans} NaN entries of {volume.size}'
        else:
            got = f'values in [{float(low):g}, {float(high):g}]'
        hint = ''
        if nans or np.float64(high) == np.inf:
            hint = ' (give impossible disparities, such as x < d, the worst cost 1.0)'
        elif -1.0 - _COST_TOLERANCE <= np.float64(low) < 0:
            hint = ' (a similarity s in [-1, 1], higher = better, goes in as (1 - s) / 2)'
        elif np.float64(low) >= 0:
            hint = ' (divide the costs by the largest one the matcher can give)'
        raise InputError(f'{name} must hold finite costs in [0, 1]; got {got}{hint}')
    return np.ascontiguousarray(volume, dtype=np.float32)


def _as_disparity(name: str, disparity: Any, shape: tuple[int, int]) -> np.ndarray:
    if not isinstance(disparity, np.ndarray):
        raise InputError(f'{name} must be a numpy array; got {type(disparity).__name__}')
    if disparity.dtype.kind not in _REAL_KINDS:
        raise InputError(
            f'{name} must hold real numbers (float or int); got dtype {disparity.dtype}'
        )
    if disparity.shape != shape:
        raise InputError(f'{name} must have shape {shape} (H, W); got {disparity.shape}')
    return np.asarray(disparity, dtype=np.float32)



def check_learned_options(matcher: object, weights: object, max_disparity: object) -> int:
    """Check the options a learned method loads its weights by; returns D as an int.

    Raises:
        ConfigError: ``matcher`` not a non-empty str (None skipped the weights' matcher check
            and then refused every input; 5 asked to train weights for matcher 5), ``weights``
            neither None nor a path (``Path()`` raised a bare TypeError), or ``max_disparity``
            not an integer ≥ 1 (``int()`` took '64' or truncated 64.5).
    """
    if not isinstance(matcher, str) or not matcher:
        raise ConfigError(
            f'matcher must be a non-empty str (a matcher name); got '
            f'{type(matcher).__name__} {matcher!r}'
        )
    if weights is not None and not isinstance(weights, (str, os.PathLike)):
        raise ConfigError(
            'weights must be a path (str or os.PathLike) or None for the shipped weights; '
            f'got {type(weights).__name__} {weights!r}'
        )
    if not is_int(max_disparity) or max_disparity < 1:  # type: ignore[operator]
        raise ConfigError(f'max_disparity must be an integer ≥ 1; got {max_disparity!r}')
    return int(max_disparity)  # type: ignore[call-overload]

@dataclass(frozen=True, eq=False)
class ConfidenceInputs:
    """Everything a confidence method may look at for one stereo pair.

    Arrays are checked on construction and converted to float32 (no copy if they already are).
    Cost volumes must be real (float or int) and lie in [0, 1] (a rounding slack of 1e-4 is
    allowed), which also excludes NaN and ±inf; disparities must be real (NaN = invalid).
    A volume of another matcher goes in as such costs, lower = better: raw costs divided by
    the largest one the matcher can give (a fixed bound, not the frame's maximum, so that
    ``mlm``'s sigma and a threshold mean the same on every frame), impossible disparities
    (``x < d``) at 1.0, and a similarity ``s`` (higher = better, NCC or a cosine in [-1, 1])
    as ``(1 - s) / 2``, or ``1 - s`` for one in [0, 1]: nothing here can tell a similarity in
    [0, 1] from a cost, and taken as a cost it ranks every pixel the wrong way round.

    Attributes:
        cost_volume: (D, H, W) float32 left-reference costs in [0, 1], 0 = perfect match;
            ``[d, y, x]`` matches left ``(y, x)`` with right ``(y, x - d)``.
        disparity: (H, W) float32 left disparity (winner-takes-all), NaN = invalid.
        image: (H, W) or (H, W, 3) uint8 left image (RGB order if colour).
        cost_volume_right: Optional (D, H, W) float32 right-reference costs; ``[d, y, x]``
            matches right ``(y, x)`` with left ``(y, x + d)``.
        disparity_right: Optional (H, W) float32 right disparity, NaN = invalid.
        matcher: Name of the matcher that produced the volume (learned methods check it);
            ``''`` = unknown.
        first_column: Image column of the arrays' column 0: 0 for whole images; a crop of
            columns ``x0:`` passes ``x0``, so that what holds at the image's left edge (one
            candidate with a partner in column 0, see ``handcrafted``) is not applied to the
            crop's.

    Raises:
        InputError: A wrong type, dtype or shape, costs outside [0, 1] (NaN included), an image
            that is not uint8, a matcher that is not a str, or a ``first_column`` that is not
            an integer ≥ 0.
    """

    cost_volume: np.ndarray
    disparity: np.ndarray
    image: np.ndarray
    cost_volume_right: np.ndarray | None = None
    disparity_right: np.ndarray | None = None
    matcher: str = ''
    first_column: int = 0

    def __post_init__(self) -> None:
        volume = _as_volume('cost_volume', self.cost_volume)
        shape = (volume.shape[1], volume.shape[2])
        # An (H, W, D) volume (the layout of many matchers and networks) read as (D, H, W)
        # fails the disparity's or the image's shape below; say why.
        for field in ('disparity', 'image'):
            value = getattr(self, field)
            found = value.shape[:2] if isinstance(value, np.ndarray) else None
            if found is not None and found != shape and found == volume.shape[:2]:
                raise InputError(
                    f'cost_volume must be (D, H, W); got shape {volume.shape}, which is '
                    f"(H, W, D) for the {field}'s {found}: pass volume.transpose(2, 0, 1)"
                )
        object.__setattr__(self, 'cost_volume', volume)
        object.__setattr__(self, 'disparity', _as_disparity('disparity', self.disparity, shape))
        image = self.image
        if not isinstance(image, np.ndarray) or image.shape[:2] != shape or not (
            image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
        ):
            got = image.shape if isinstance(image, np.ndarray) else type(image).__name__
            raise InputError(f'image must be {shape} or {shape + (3,)}; got {got}')
        if image.dtype != np.uint8:
            raise InputError(f'image must be uint8 (intensities 0..255); got dtype {image.dtype}')
        if not isinstance(self.matcher, str):
            raise InputError(
                "matcher must be a str (a matcher name, or '' if unknown); "
                f'got {type(self.matcher).__name__}'
            )
        if not is_int(self.first_column) or self.first_column < 0:
            raise InputError(
                f'first_column must be an integer ≥ 0 (the image column of column 0 of the '
                f'arrays); got {self.first_column!r}'
            )
        object.__setattr__(self, 'first_column', int(self.first_column))
        if self.cost_volume_right is not None:
            right = _as_volume('cost_volume_right', self.cost_volume_right)
            if right.shape != volume.shape:
                raise InputError(
                    f'cost_volume_right must have the shape of cost_volume {volume.shape}; '
                    f'got {right.shape}'
                )
            object.__setattr__(self, 'cost_volume_right', right)
        if self.disparity_right is not None:
            object.__setattr__(
                self,
                'disparity_right',
                _as_disparity('disparity_right', self.disparity_right, shape),
            )

    def __repr__(self) -> str:
        # The dataclass's own printed every array (96 lines for a 32 × 48 × 64 volume), the
        # whole of a notebook cell's output.
        right = '' if self.cost_volume_right is None else ', with the right-view volume'
        column = f', first_column={self.first_column}' if self.first_column else ''
        return (f'ConfidenceInputs(D={self.max_disparity}, {self.shape[1]}×{self.shape[0]} px, '
                f'image {self.image.shape}, matcher={self.matcher!r}{right}{column})')

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the maps."""
        return (self.cost_volume.shape[1], self.cost_volume.shape[2])

    @property
    def max_disparity(self) -> int:
        """Cost-volume depth D."""
        return int(self.cost_volume.shape[0])


def _finite_clip(values: np.ndarray) -> np.ndarray:
    # clip already sends ±inf to the nearest end; only NaN (no order) needs a value: 0. An
    # isfinite mask sent +inf to 0 as well, below 1e30's 1: the map was not increasing.
    values = np.asarray(values, dtype=np.float32)
    return np.where(np.isnan(values), np.float32(0.0), np.clip(values, 0.0, 1.0)).astype(
        np.float32
    )


class ConfidenceMethod(ABC):
    """A confidence measure: ``method(inputs) -> (H, W) float32``, higher = more confident.

    Subclasses are (frozen) dataclasses whose fields are the method's options; they set
    :attr:`needs_right` when they read the right-reference volume or disparity, and
    :attr:`probabilistic` when their value is meant as the probability that the disparity is
    correct (networks trained with binary cross-entropy on the correctness label): only then
    does ``1 − confidence`` estimate an error rate (:mod:`cva_confidence_ros.calibration`).
    """

    needs_right: ClassVar[bool] = False
    probabilistic: ClassVar[bool] = False
    #: Smallest cost-volume depth D the method is defined for (2 for those that need a
    #: second-best cost).
    min_depth: ClassVar[int] = 1

    @abstractmethod
    def __call__(self, inputs: ConfidenceInputs) -> np.ndarray:
        """Compute the (H, W) float32 confidence map of ``inputs``."""

    def to_unit_interval(self, confidence: np.ndarray) -> np.ndarray:
        """Map this method's confidence into [0, 1] by a fixed, increasing function.

        The published confidence image and ``confidence_threshold`` live in [0, 1]. The map is
        the same for every frame (no per-frame scaling), so a threshold means the same thing on
        every frame, and it keeps the order of the values. The default clips, which is exact for
        methods that already give probabilities (``cva_net``, ``mlm``); methods with other
        ranges override it.

        Args:
            confidence: (H, W) float32 as returned by :meth:`__call__`.

        Returns:
            (H, W) float32 in [0, 1]; NaN becomes 0, ±inf the nearest end.
        """
        return _finite_clip(confidence)

    @classmethod
    def from_options(cls, **options: Any) -> ConfidenceMethod:
        """Factory for the registry: build from options, dropping :data:`GENERIC_OPTIONS`.

        The method's own options are its dataclass fields, or for a method that is no
        dataclass (``cva_net``) the named parameters of its ``__init__``, which may be generic
        options too (``max_disparity``, ``weights``): those are passed, not dropped.

        Raises:
            ConfigError: An option that is neither generic nor a field of the method.
        """
        own: set[str] = (
            {f.name for f in fields(cls)} if is_dataclass(cls) else _init_parameters(cls)
        )
        unknown = set(options) - own - GENERIC_OPTIONS
        if unknown:
            raise ConfigError(
                f'unknown options {sorted(unknown)} for {cls.__name__}; expected {sorted(own)} '
                f'or the generic {sorted(GENERIC_OPTIONS)}'
            )
        return cls(**{key: value for key, value in options.items() if key in own})

    def _require_right(self, inputs: ConfidenceInputs) -> np.ndarray:
        if inputs.cost_volume_right is None:
            raise InputError(
                f'{type(self).__name__} needs the right-reference cost volume; '
                'got cost_volume_right=None'
            )
        return inputs.cost_volume_right


def _init_parameters(cls: type) -> set[str]:
    """Names of the keyword parameters of ``cls.__init__`` (no ``*args`` / ``**kwargs``)."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    parameters = inspect.signature(cls).parameters.values()
    return {p.name for p in parameters if p.kind in kinds}


ConfidenceFactory = Callable[..., ConfidenceMethod]

#: name → factory ``(**options) -> ConfidenceMethod``.
CONFIDENCE_METHODS: Registry[ConfidenceFactory] = Registry('confidence method')


def compute_confidence(name: str, inputs: ConfidenceInputs, **options: Any) -> np.ndarray:
    """Build the method registered as ``name`` with ``options`` and apply it to ``inputs``.

    Args:
        name: Registered method name (``pkrn``, ``mlm``, ``lrd``, ``lrc``, ``score``, ...).
        inputs: Cost volume(s), disparity and image of one pair.
        **options: Method options; the pipeline's generic options are accepted and ignored.

    Returns:
        (H, W) float32 confidence, higher = more confident.

    Raises:
        ConfigError: Unknown name or option.
        InputError: The method needs the right view and ``inputs`` has none.
    """
    method = CONFIDENCE_METHODS.get(name)(**options)
    return np.asarray(method(inputs), dtype=np.float32)


def is_probabilistic(name: str) -> bool:
    """Whether the registered method ``name`` gives the probability of a correct disparity.

    Raises:
        ConfigError: Unknown method name.
    """
    factory = CONFIDENCE_METHODS.get(name)
    # A factory that is a classmethod (``MaximumLikelihood.from_options``) is a bound method:
    # getattr on it reads the function's attributes, never the class's ``probabilistic``.
    owner = factory.__self__ if inspect.ismethod(factory) else factory
    return bool(getattr(owner, 'probabilistic', False))
