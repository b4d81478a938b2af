"""What the level-camera trace and the two-step draw of episode starts save: the
environment's random-action rollout and the whole training update, as they are and with
both switched off (the general box test for every camera, and a running count with an
argmax over the whole grid for the starts), each jitted, timed in turns in one process.

    python -m a2catvn_jax.bench.level_trace_cost [--config configs/house_rooms_cpu.yaml] [--rounds 6]

The two programs compute the same function: the script checks that one update of each
from the same state gives the same losses to float rounding.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import a2catvn_jax.env.navenv as navenv
import a2catvn_jax.env.raycast as render
from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.update import frames_per_update, make_update
from a2catvn_jax.bench.throughput import random_steps
from a2catvn_jax.config import load_config
from a2catvn_jax.env import NavEnv


def _running_count_index(key, mask):
    """The start draw without its two steps: the first index where the running count of
    `mask` exceeds k."""
    count = mask.sum()
    k = jnp.minimum(jnp.floor(jax.random.uniform(key) * count), count - 1)
    return jnp.argmax(jnp.cumsum(mask) > k)


def _build(cfg, steps: int):
    env = NavEnv(cfg.env)
    rollout = random_steps(env, steps)
    env_state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    env_state = jax.block_until_ready(rollout(env_state, jax.random.PRNGKey(1)))
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    state = init(jax.random.PRNGKey(0))
    compiled = update.lower(state).compile()
    return rollout, env_state, compiled, state


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/house_rooms_cpu.yaml")
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--updates", type=int, default=10, help="updates (and rollouts) timed per round")
    a = p.parse_args()
    cfg = load_config(a.config)
    steps = cfg.train.rollout_length
    built = {"as it is": _build(cfg, steps)}
    saved = render.trace_level, navenv.uniform_index
    render.trace_level = lambda geom, cam_pos, yaw, dirs, spec: render.trace(geom, cam_pos, dirs)
    navenv.uniform_index = _running_count_index
    try:
        built["both off"] = _build(cfg, steps)
    finally:
        render.trace_level, navenv.uniform_index = saved
    # The same function: the first update of each, from the same initial state.
    states, first = {}, {}
    for k, (_, _, update, state) in built.items():
        states[k], first[k] = update(state)
    np.testing.assert_allclose(float(first["as it is"]["loss/total"]), float(first["both off"]["loss/total"]), rtol=1e-3)
    env_ms = {k: [] for k in built}
    fps = {k: [] for k in built}
    for r in range(a.rounds):
        for k in (list(built) if r % 2 == 0 else list(built)[::-1]):
            rollout, env_state, update, _ = built[k]
            t0 = time.perf_counter()
            for i in range(a.updates):
                env_state = rollout(env_state, jax.random.PRNGKey(i))
            jax.block_until_ready(env_state)
            env_ms[k].append((time.perf_counter() - t0) / a.updates * 1e3)
            s = states[k]
            t0 = time.perf_counter()
            for _ in range(a.updates):
                s, m = update(s)
            jax.block_until_ready(m)
            states[k] = s
            fps[k].append(a.updates * frames_per_update(cfg) / (time.perf_counter() - t0))
    print(f"{a.config}: {cfg.env.num_envs} environments, {steps}-step rollouts, {a.rounds} rounds in turns")
    print(f"{'':>10}  {'env rollout ms (median)':>24}  {'train frames/s (median)':>24}  train frames/s by round")
    for k in built:
        print(f"{k:>10}  {np.median(env_ms[k]):24.1f}  {np.median(fps[k]):24.0f}  "
              + " ".join(f"{x:.0f}" for x in fps[k]))


if __name__ == "__main__":
    main()
