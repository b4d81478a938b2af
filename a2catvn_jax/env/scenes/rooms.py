"""Single furnished rooms: a one-room house."""

from __future__ import annotations

from typing import Optional

from .houses import house
from .spec import Scene


def single_room(
    seed: int,
    size: tuple[float, float] = (4.0, 5.0),
    room_type: Optional[str] = None,
    height: float = 2.6,
    **kwargs,
) -> Scene:
    """One furnished room (in the spirit of an AI2-THOR room).

    size: (min, max) side length in metres; both sides are drawn in that range (pass
    equal values for a fixed square room). room_type: one of the house room types, or
    None for a seeded random choice. Extra keyword arguments go to `house`.
    """
    room_types = None if room_type is None else [room_type]
    kwargs.setdefault("name", f"room_{seed}")
    return house(seed, grid=(1, 1), room_size=size, height=height, room_types=room_types, **kwargs)


__all__ = [
    "single_room",
]
