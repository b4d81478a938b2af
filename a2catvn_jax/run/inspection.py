"""Look inside a trained agent: restore a checkpoint, record an episode with the network's
depth and segmentation predictions, and draw them beside the ground truth and the path.

    from a2catvn_jax.run import inspection
    agent = inspection.load_agent("runs/quickstart")           # latest checkpoint, training houses
    rec = inspection.record(agent, steps=200, seed=0)          # environment 0, step by step
    inspection.prediction_figure(agent, rec, t=10)             # matplotlib Figure
    inspection.path_map(agent, rec, episode=0)                 # [size, size, 3] uint8 top-down map
    inspection.gradient_norms("runs/quickstart", batches=8)    # which loss drives the shared layers there

Used by `notebooks/evaluate.ipynb`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure  # no pyplot: works with any backend; notebooks display it

from a2catvn_jax.agent.acting import ACTION_RULES, act_as, initial_agent, observe
from a2catvn_jax.agent.losses import DEPTH_SCALE, downsize_mean
from a2catvn_jax.agent.networks import VN_HEADS, Networks, make_networks
from a2catvn_jax.agent.update import make_grad_norms, make_update
from a2catvn_jax.env import make_env
from a2catvn_jax.env.scenes.spec import SEGMENTATION_COLORS
from a2catvn_jax.env.world import houses_at
from a2catvn_jax.run.checkpoint import Checkpointer
from a2catvn_jax.run.restore import house_env, locate
from a2catvn_jax.run.topdown import TopdownMap

RECORD_OBS = ("rgb", "depth", "segmentation_rgb", "target_rgb", "target_depth", "target_segmentation_rgb")
RECORD_INFO = ("pose", "target_pose", "scene", "goal")


@dataclasses.dataclass
class Agent:
    """A restored run: its configuration (at evaluation settings), environment, network and parameters."""

    workdir: Path
    run_cfg: object
    cfg: object
    env: object
    networks: Networks
    params: object
    step: int
    frames: int

    @property
    def trained_vn_heads(self) -> tuple[str, ...]:
        """The depth / segmentation heads that had a non-zero loss weight in training."""
        w = self.run_cfg.train.loss_weights
        return tuple(h for h in VN_HEADS if getattr(w, h) > 0)


def load_agent(workdir, step: Optional[int] = None, houses: str = "train", overrides: Sequence[str] = ()) -> Agent:
    """Restore checkpoint `step` (default: the latest) of the run in `workdir`.

    `houses` and `overrides` are those of `python -m a2catvn_jax.evaluate` (the network's
    keys cannot change). Raises `CheckpointError`, `ConfigError` and `ValueError`.
    """
    run = locate(workdir, step, overrides)
    env = house_env(run.cfg.env, houses)
    r = run.restore()
    return Agent(r.workdir, r.run_cfg, r.cfg, env, r.networks, r.params, r.step, r.frames)


def gradient_norms(workdir, step: Optional[int] = None, batches: int = 8) -> dict:
    """Which loss drives the shared features at checkpoint `step` (default: the latest) of
    the run in `workdir`: the norm of each weighted loss term's gradient on the conv
    layers every head shares (`update.make_grad_norms`, what `train.grad_norm_every` logs),
    on `batches` batches collected from the checkpoint's whole training state: the batch
    its next update would have learned from (the state's own key; the values a
    `grad_norm_every` log row of that update holds), then batches from keys folded from
    it. Returns {"step", "batches": [{"grad_norm/TERM": norm, ...}, ...], "mean": {...}}.
    Raises `CheckpointError` for a missing or unreadable checkpoint."""
    if batches < 1:
        raise ValueError(f"batches must be >= 1, got {batches}")
    run = locate(workdir, step)
    cfg = run.run_cfg
    env = make_env(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    template = jax.eval_shape(make_update(env, networks, cfg).init, jax.random.PRNGKey(0))
    ckpt = Checkpointer(run.workdir, create=False)
    try:
        state, _ = ckpt.restore(template, cfg, run.step)
    finally:
        ckpt.close()
    norms = make_grad_norms(env, networks, cfg)
    houses = houses_at(env, cfg.train.new_houses_every, run.step)  # with train.new_houses_every: where the run was
    keys = [state.key] + [jax.random.fold_in(state.key, i) for i in range(1, batches)]
    rows = [{k: float(v) for k, v in jax.device_get(norms(state.replace(key=k), houses)).items()} for k in keys]
    return {"step": run.step, "batches": rows, "mean": {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}}


def record(agent: Agent, steps: int, *, seed: int = 0, policy: str = "sample", env_index: int = 0) -> dict:
    """`steps` steps of all environments; returns environment `env_index`'s record as numpy
    arrays with a leading time axis: the observation before each step (RECORD_OBS), its
    pose / target / scene / goal, the action, reward, done and success of the step, and
    the network's predictions at the ground truth's resolution: depth_pred (metres),
    segmentation_pred and target_segmentation_pred (RGB in [0, 1])."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if policy not in ACTION_RULES:
        raise ValueError(f"policy must be sample, greedy or random, got {policy!r}")
    env, networks = agent.env, agent.networks
    if not 0 <= env_index < env.num_envs:
        raise ValueError(f"env_index must be in [0, {env.num_envs}), got {env_index}")
    colors = jnp.asarray(SEGMENTATION_COLORS, jnp.float32) / 255.0

    def as_rgb(seg):
        if agent.cfg.agent.segmentation_loss == "cross_entropy":
            return colors[jnp.argmax(seg, -1)]
        return jnp.clip(seg, 0.0, 1.0)

    @jax.jit
    def step(params, target_feats, env_state, agent_state, key):
        core, action = act_as(policy, networks, params, target_feats, agent_state, env_state.obs, key)
        obs = env_state.obs
        conv4, _ = networks.encode(params, obs.rgb, target_feats[obs.target_index])
        pred = networks.vn_heads(params, conv4)
        nxt = env.step(env_state, action)
        out = {k: getattr(obs, k)[env_index] for k in RECORD_OBS}
        out.update({k: getattr(env_state.info, k)[env_index] for k in RECORD_INFO})
        out.update(action=action[env_index], reward=nxt.reward[env_index], done=nxt.done[env_index],
                   success=nxt.metrics["success"][env_index],
                   depth_pred=pred["depth"][env_index] / DEPTH_SCALE,
                   segmentation_pred=as_rgb(pred["segmentation"][env_index]),
                   target_segmentation_pred=as_rgb(pred["target_segmentation"][env_index]))
        return nxt, observe(core, action, nxt), out

    key = jax.random.PRNGKey(seed)
    key, k_reset = jax.random.split(key)
    env_state = jax.jit(lambda k: env.reset(k, complexity=agent.cfg.env.complexity))(k_reset)
    agent_state = initial_agent(networks, env.num_envs)
    target_feats = jax.jit(networks.target_stream)(agent.params, env.target_images()["rgb"])
    rows = []
    for k in jax.random.split(key, steps):
        env_state, agent_state, out = step(agent.params, target_feats, env_state, agent_state, k)
        rows.append(jax.device_get(out))
    return {name: np.stack([r[name] for r in rows]) for name in rows[0]}


def episodes(rec: dict) -> list[tuple[int, int]]:
    """(first, last) step indices of the episodes in a record (the last may be unfinished)."""
    ends = list(np.nonzero(rec["done"])[0])
    starts = [0] + [e + 1 for e in ends]
    spans = [(s, e) for s, e in zip(starts, ends)]
    if starts[-1] < len(rec["done"]):
        spans.append((starts[-1], len(rec["done"]) - 1))
    return spans


def _downsized(image: np.ndarray, size: int) -> np.ndarray:
    """An [H, W, ...] ground-truth image averaged down to `size` rows, as the losses see it."""
    return np.asarray(downsize_mean(image[None], image.shape[0] // size)[0])


def prediction_figure(agent: Agent, rec: dict, t: int):
    """A matplotlib Figure for step `t`: observation and target; depth, observation
    segmentation and target segmentation, ground truth above the prediction."""
    if not 0 <= t < len(rec["done"]):
        raise ValueError(f"t must be in [0, {len(rec['done'])}), got {t}")
    a = rec["depth_pred"].shape[1]
    trained = agent.trained_vn_heads
    panels = [
        ("observation", rec["rgb"][t], None),
        ("target", rec["target_rgb"][t], None),
        ("depth", _downsized(rec["depth"][t], a), rec["depth_pred"][t], "depth"),
        ("segmentation", _downsized(rec["segmentation_rgb"][t] / 255.0, a), rec["segmentation_pred"][t], "segmentation"),
        ("target segmentation", _downsized(rec["target_segmentation_rgb"][t] / 255.0, a),
         rec["target_segmentation_pred"][t], "target_segmentation"),
    ]
    fig = Figure(figsize=(2.0 * len(panels), 4.2))
    axes = fig.subplots(2, len(panels))
    vmax = float(max(rec["depth"][t].max(), 1e-3))
    for col, panel in enumerate(panels):
        top, bottom = axes[0][col], axes[1][col]
        if panel[2] is None:
            top.imshow(panel[1])
            top.set_title(panel[0], fontsize=8)
            bottom.set_visible(False)
        else:
            name, truth, pred, head = panel
            kw = {"cmap": "viridis", "vmin": 0.0, "vmax": vmax} if name == "depth" else {}
            top.imshow(truth, **kw)
            top.set_title(f"{name}: truth", fontsize=8)
            bottom.imshow(pred, **kw)
            bottom.set_title(f"prediction{'' if head in trained else ' (head untrained)'}", fontsize=8)
        for ax in (top, bottom):
            ax.set_axis_off()
    fig.suptitle(f"{agent.workdir} update {agent.step}, step {t}: action {agent.env.action_names[int(rec['action'][t])]}",
                 fontsize=8)
    fig.tight_layout()
    return fig


def path_map(agent: Agent, rec: dict, episode: int = 0, size: int = 256) -> np.ndarray:
    """[size, size, 3] uint8: the top-down map of an episode's scene with its path, final
    pose and target pose."""
    spans = episodes(rec)
    if not 0 <= episode < len(spans):
        raise ValueError(f"episode must be in [0, {len(spans)}), got {episode}")
    first, last = spans[episode]
    scene = int(rec["scene"][first])
    goal = int(rec["goal"][first])
    target_scene = int(np.asarray(agent.env.world.arrays.target_scene)[scene, goal])
    target = rec["target_pose"][first] if target_scene == scene else None
    outcome = "success" if rec["success"][last] else ("failed" if rec["done"][last] else "unfinished")
    text = f"{episode + 1}: {last - first + 1} steps, {outcome}"
    return TopdownMap(agent.env.world.scenes[scene], size).render(rec["pose"][first : last + 1, :2],
                                                                 rec["pose"][last], target, text)
