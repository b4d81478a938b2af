"""Per-process caches of values that are costly to make (compiled functions, measured
render rates), each named, bounded and clearable: one mechanism instead of ad-hoc globals."""

from __future__ import annotations

import collections
from typing import Callable, Hashable, Optional, TypeVar

V = TypeVar("V")


class Memo:
    """`get(key, make)`: the value made once per key, the `keep` most recently used kept
    (all of them when `keep` is None)."""

    def __init__(self, name: str, keep: Optional[int] = None):
        self.name = name
        self.keep = keep
        self._values: collections.OrderedDict = collections.OrderedDict()

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        if key not in self._values:
            self._values[key] = make()
            if self.keep is not None and len(self._values) > self.keep:
                self._values.popitem(last=False)
        self._values.move_to_end(key)
        return self._values[key]

    def __contains__(self, key: Hashable) -> bool:
        return key in self._values

    def values(self) -> list:
        return list(self._values.values())

    def clear(self) -> None:
        self._values.clear()

    def __len__(self) -> int:
        return len(self._values)
