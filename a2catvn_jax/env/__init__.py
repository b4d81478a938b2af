"""The navigation environment: scenes, their geometry, the ray-cast camera, occupancy
grids, the world of goals and target images, and `NavEnv` (reset / step)."""

from a2catvn_jax.env.navenv import ACTION_SETS, NavEnv, State

__all__ = ["ACTION_SETS", "NavEnv", "State"]
