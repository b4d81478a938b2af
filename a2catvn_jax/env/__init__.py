"""The navigation environment: scenes, their geometry, the ray-cast camera, occupancy
grids, the world of goals and target images, and `NavEnv` (reset / step)."""

from a2catvn_jax.env.navenv import ACTION_SETS, Info, NavEnv, Observation, State, action_names
from a2catvn_jax.env.world import World, WorldArrays

__all__ = ["ACTION_SETS", "action_names", "Info", "NavEnv", "Observation", "State", "World", "WorldArrays"]
