"""The error a scene that cannot be used raises."""

from __future__ import annotations

from a2catvn_jax.errors import UserError


class SceneError(ValueError, UserError):
    """A scene (usually a user's MJCF file) that cannot be used; the one-line message
    names the scene or file, the problem, and the geom at fault where there is one."""


__all__ = ["SceneError"]
