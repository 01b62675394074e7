"""Registries keyed by name: matchers and confidence methods are selected by a string."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from cva_confidence_ros.errors import ConfigError

__all__ = ['Registry']

T = TypeVar('T')


class Registry(Generic[T]):
    """A name → object mapping with a decorator to register and a clear error on lookup.

    Args:
        kind: What the registry holds, used in error messages (e.g. ``'matcher'``).
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._items: dict[str, T] = {}

    def register(self, name: str) -> Callable[[T], T]:
        """Register the decorated object under ``name``.

        Raises:
            ConfigError: ``name`` is not a non-empty str, or is registered already.
        """
        # Names come from configuration, always str: an int name could never be selected, and
        # sorted() of mixed names broke names() and every unknown-name error (a bare TypeError).
        if not isinstance(name, str) or not name:
            raise ConfigError(
                f'{self.kind} name must be a non-empty str; got {type(name).__name__} {name!r}'
            )

        def decorator(obj: T) -> T:
            if name in self._items:
                raise ConfigError(f'{self.kind} {name!r} is registered twice')
            self._items[name] = obj
            return obj

        return decorator

    def add(self, name: str, obj: T) -> None:
        """Register ``obj`` under ``name`` (non-decorator form)."""
        self.register(name)(obj)

    def get(self, name: str) -> T:
        """Return the object registered as ``name``; raise :class:`ConfigError` if unknown."""
        try:
            return self._items[name]
        except (KeyError, TypeError):  # TypeError: an unhashable name, e.g. a list
            raise ConfigError(
                f'unknown {self.kind} {name!r}; expected one of {sorted(self._items)}'
            ) from None

    def names(self) -> list[str]:
        """Registered names, sorted."""
        return sorted(self._items)

    def __contains__(self, name: object) -> bool:
        try:
            return name in self._items
        except TypeError:  # an unhashable name is no registered one
            return False

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())
