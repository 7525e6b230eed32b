"""A least-recently-used store of computed values, bounded by entries and by bytes: what the world model keeps of the
inputs its training steps see again (decoded views, processed pixels, a frame's Gaussians and candidates).

Hand-written (a dozen lines): ``functools.lru_cache`` bounds entries only, and cachetools, which bounds sizes, is a
transitive dependency of MLflow here, not one of ours.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

V = TypeVar("V")


class LRU(Generic[V]):
    """Values by key, at most ``items`` of them and ``nbytes`` of ``size(value)`` in all (None: no bound); the least
    recently used go first, and the last one stays whatever its size."""

    def __init__(self, items: int | None = None, nbytes: int | None = None, size: Callable[[V], int] | None = None):
        if nbytes is not None and size is None:
            raise ValueError("LRU: a bound in bytes needs size=, what a value weighs")
        self.items, self.nbytes, self._size = items, nbytes, size
        self._values: OrderedDict[Hashable, V] = OrderedDict()
        self.total = 0
        """``size`` of the values held, summed."""

    def __len__(self) -> int:
        return len(self._values)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._values

    def get(self, key: Hashable, compute: Callable[[], V]) -> V:
        """The value under ``key``, from ``compute()`` the first time (and again once it has been dropped)."""
        if key in self._values:
            self._values.move_to_end(key)
            return self._values[key]
        value = compute()
        self._values[key] = value
        self.total += self._size(value) if self._size else 0
        while len(self._values) > 1 and (
            (self.items is not None and len(self._values) > self.items)
            or (self.nbytes is not None and self.total > self.nbytes)
        ):
            dropped = self._values.popitem(last=False)[1]
            self.total -= self._size(dropped) if self._size else 0
        return value
