"""What each environment's `mjx.Data` costs a step: the environment step against its
data work alone (the new episodes' data, the select between old and new, the agent's
pose written in), both jitted, timed in turns in one process.

    python -m a2catvn_jax.bench.world_model_cost [--config configs/image_goals_cpu.yaml] [--batch 256]
"""

import argparse
import time

import jax
import jax.numpy as jnp

from a2catvn_jax.config import load_config
from a2catvn_jax.env.navenv import NavEnv, select_where


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/image_goals_cpu.yaml")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    a = p.parse_args()
    cfg = load_config(a.config, [f"env.num_envs={a.batch}"])
    env = NavEnv(cfg.env)
    w = env.world.arrays
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    step = jax.jit(env.step)

    def data_work(s, done):
        fresh = env.world.scene_data(w, s.info.scene)
        d = jax.tree_util.tree_map(lambda x, y: select_where(done, x, y), fresh, s.data)
        return env.world.place_agent(d, s.info.pose)

    data_fn = jax.jit(data_work)
    actions = jax.random.randint(jax.random.PRNGKey(1), (a.steps, a.batch), 0, env.num_actions)
    done = jnp.arange(a.batch) % 7 == 0
    jax.block_until_ready((step(state, actions[0]), data_fn(state, done)))
    t_step, t_data = [], []
    for _ in range(a.repeats):
        t0, s = time.perf_counter(), state
        for k in range(a.steps):
            s = step(s, actions[k])
        jax.block_until_ready(s)
        t_step.append((time.perf_counter() - t0) / a.steps)
        t0 = time.perf_counter()
        for _ in range(a.steps):
            d = data_fn(state, done)
        jax.block_until_ready(d)
        t_data.append((time.perf_counter() - t0) / a.steps)
    nbytes = sum(x.nbytes for x in jax.tree_util.tree_leaves(state.data)) / a.batch
    print(f"{a.config} B={a.batch} {cfg.env.render.image_size} px: step {min(t_step) * 1e3:.2f} ms, "
          f"data work {min(t_data) * 1e3:.3f} ms ({min(t_data) / min(t_step):.1%} of a step); "
          f"mjx.Data {nbytes:,.0f} bytes per environment")


if __name__ == "__main__":
    main()
