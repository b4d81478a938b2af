"""The navigation environment: scenes, their geometry, the ray-cast camera, occupancy
grids, the world of goals and target images, and `NavEnv` (reset / step); and
`SyntheticEnv`, a rendering-free stand-in with the same interface for testing agent code."""

from a2catvn_jax.configio import ConfigError
from a2catvn_jax.env.navenv import ACTION_SETS, Info, NavEnv, Observation, State, action_names
from a2catvn_jax.env.synthetic import SyntheticEnv
from a2catvn_jax.env.world import World, WorldArrays


def make_env(cfg, world=None, seed_offset: int = 0):
    """The environment `cfg` (an `EnvConfig`) names by `kind`: a `NavEnv` over `world`
    (default: built from `cfg`), or a `SyntheticEnv`."""
    if cfg.kind == "synthetic":
        if world is not None:
            raise ValueError("the synthetic environment is built from its configuration alone: pass no world")
        return SyntheticEnv(cfg, seed_offset)
    return NavEnv(cfg, world, seed_offset)


def require_world(cfg, what: str) -> None:
    """A one-line `ConfigError` when `what` (e.g. "evaluation") needs the MuJoCo world of
    houses and `cfg` (an `EnvConfig`) is the synthetic environment."""
    if cfg.kind != "mujoco":
        raise ConfigError(f"{what} needs the MuJoCo environment (houses, an oracle, held-out sets): this run's "
                          f"env.kind is {cfg.kind!r}, a test bench for training code")


__all__ = ["ACTION_SETS", "action_names", "Info", "make_env", "NavEnv", "Observation", "require_world", "State",
           "SyntheticEnv", "World", "WorldArrays"]
