"""A dict that keeps its most recently used entries only.

The caches of the algorithms are keyed by what the data decides - an image size, a class tuple, a bin count - and a
stream (or an attacker) decides the data: a cache that only grows would grow with it. Every such cache is a
:class:`BoundedCache`, sized for the handful of keys a real stream uses.
"""

from __future__ import annotations

from collections import OrderedDict


class BoundedCache(OrderedDict):
    """At most ``size`` entries; ``get`` and ``[]`` count as a use; storing a new key beyond ``size`` drops the least
    recently used one."""

    def __init__(self, size: int):
        super().__init__()
        if int(size) < 1:
            raise ValueError(f"a cache needs room for at least one entry, got {size}")
        self.size = int(size)

    def __getitem__(self, key):
        value = super().__getitem__(key)
        self.move_to_end(key)
        return value

    def get(self, key, default=None):
        if key in self:
            return self[key]
        return default

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        self.move_to_end(key)
        while len(self) > self.size:
            self.popitem(last=False)
