"""Seeded procedural scenes by kind: multi-room houses, single rooms and mazes.

Every generator is a pure function of its seed and arguments and returns a host-side
`Scene` (see `spec.py`); `builder.py` states the geometry conventions they share.
"""

from __future__ import annotations

from typing import Callable, Iterator

import numpy as np

from .houses import house
from .mazes import maze
from .rooms import single_room
from .spec import Scene

GENERATORS: dict[str, Callable[..., Scene]] = {"house": house, "room": single_room, "maze": maze}


def make_scenes(kind: str, num: int, seed: int, **kwargs) -> list[Scene]:
    """`num` scenes of one kind ("house", "room" or "maze") with seeds derived from `seed`.

    Scene i uses its own seed drawn from numpy's SeedSequence(seed), so the list is
    reproducible and the scenes differ from each other. kwargs go to the generator.
    """
    if num < 0:
        raise ValueError(f"num must be >= 0, got {num}")
    return list(scene_stream(kind, num, seed, **kwargs))  # which checks the kind


def scene_stream(kind: str, num: int, seed: int, **kwargs) -> Iterator[Scene]:
    """`make_scenes(kind, num, seed, **kwargs)`'s scenes one at a time, each generated only
    when it is asked for (the first k are the same whatever `num` is)."""
    if kind not in GENERATORS:
        raise ValueError(f"unknown scene kind {kind!r}; valid kinds: {sorted(GENERATORS)}")
    seeds = np.random.SeedSequence(seed).generate_state(max(num, 1), dtype=np.uint32)[:num]
    fn = GENERATORS[kind]
    return (fn(int(s), name=f"{kind}_{seed}_{i}", **kwargs) for i, s in enumerate(seeds))


__all__ = [
    "GENERATORS",
    "make_scenes",
    "scene_stream",
]
