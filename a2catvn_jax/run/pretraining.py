"""Supervised pre-training of the conv base with the depth and segmentation heads.

`pretrain(cfg, workdir)` renders `pretrain.dataset_size` observations at random poses
(free cells of the training scenes, random heading and camera tilt) with their depth
and segmentation ground truth, each paired with a random target image of its scene,
and trains the network's conv base and its depth / observation-segmentation /
target-segmentation heads on them with Adam for `pretrain.epochs` epochs (the losses
and weights of training: `train.loss_weights.{depth,segmentation,target_segmentation}`).
One jit-compiled step serves every batch. Each batch is split over every local device
(or the first `devices`), the parameters replicated: the same steps as on one device,
to float tolerance.

The work directory gets `config.yaml`, `pretrain_metrics.jsonl` (one row per epoch)
and the trained parameters (conv1-conv4 and the heads) as an orbax checkpoint in
`pretrained/`. `load_matching` starts a training run from them.

Like training, pre-training holds its work directory's lock (`run.workdir`) while it
writes. The parameters are written once, at the end; a run that stopped earlier (or
whose write failed, a full disk included: one line) leaves no parameters, and the next
one in that directory removes its half-written files and metrics rows, with a line.
"""

from __future__ import annotations

import functools
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp

from a2catvn_jax.agent.networks import make_networks
from a2catvn_jax.agent.types import FrameTruth
from a2catvn_jax.agent.update import frame_truth, learner, targets_of, vn_terms
from a2catvn_jax.config import save_config
from a2catvn_jax.env import NavEnv, require_world
from a2catvn_jax.errors import UserError
from a2catvn_jax.run import distributed
from a2catvn_jax.run.checkpoint import PARTIAL, io_reason, quiet_abandoned_io, silence_abandoned_reads
from a2catvn_jax.run.logger import MetricsWriter, truncate_metrics
from a2catvn_jax.run.workdir import locked

PRETRAINED_DIR = "pretrained"
TRAINED_LAYERS = ("conv1", "conv2", "conv3", "conv4", "vn")  # what the pre-training losses reach
CHUNK = 64  # dataset samples rendered per compiled call


class PretrainError(UserError, RuntimeError):
    """Pre-training cannot run as configured, or a pre-trained directory cannot be used."""


def make_dataset(cfg, env: NavEnv, size: int, key) -> dict:
    """`size` samples: rgb [N, H, W, 3] uint8, target [N] (index of a target image of the
    frame's scene), and the depth / segmentation ground truth at auxiliary resolution of
    the losses that are on (depth_gt, seg_gt)."""
    S = env.num_scenes
    max_tilt = float(np.deg2rad(env.cfg.max_tilt_deg)) if "tilt_up" in env.action_names else 0.0
    tilt_steps = np.deg2rad(30.0) * np.arange(-4, 5)
    tilts = jnp.asarray(tilt_steps[np.abs(tilt_steps) <= max_tilt + 1e-6], jnp.float32)

    @jax.jit
    def chunk(key, first):
        keys = jax.random.split(key, CHUNK + 1)
        scene = (first + jnp.arange(CHUNK, dtype=jnp.int32)) % S
        tau = jnp.ones((CHUNK,), jnp.float32)
        goal, pose, _ = env.sample_starts(keys[1:], scene, tau)
        tilt = jax.random.choice(keys[0], tilts, (CHUNK,))
        pose = pose.at[:, 3].set(tilt)
        frame = env.render_poses(scene, pose)
        truth = frame_truth(learner(cfg), frame.depth, frame.cls)
        out = {"rgb": frame.rgb, "target": env.target_index(scene, goal)}
        out.update({name: x for name, x in (("depth_gt", truth.depth), ("seg_gt", truth.segmentation)) if x is not None})
        return out

    parts = []
    for i, k in enumerate(jax.random.split(key, -(-size // CHUNK))):
        parts.append(jax.device_get(chunk(k, i * CHUNK)))
    return {name: np.concatenate([p[name] for p in parts])[:size] for name in parts[0]}


@locked("pretrain")  # one writer per work directory (run/workdir.py)
def pretrain(cfg, workdir, *, log=None, devices=None) -> dict:
    """Pre-train in `workdir` with each batch split over `devices` local devices (default:
    all); returns the parameters."""
    log = log or functools.partial(print, flush=True)
    w = cfg.train.loss_weights
    if w.depth == 0 and w.segmentation == 0 and w.target_segmentation == 0:
        raise PretrainError("pre-training needs a non-zero train.loss_weights.depth, segmentation or target_segmentation")
    workdir = Path(workdir)
    if (workdir / PRETRAINED_DIR).exists():
        raise PretrainError(f"{workdir / PRETRAINED_DIR} already exists; choose another --workdir")
    for partial in sorted(workdir.glob(f"{PRETRAINED_DIR}{PARTIAL}*")):  # a write that did not finish
        shutil.rmtree(partial, ignore_errors=True)
        log(f"removed {partial}, parameters whose write did not finish")
    if truncate_metrics(workdir, 0, name="pretrain_metrics", key="epoch"):
        log(f"removed the rows of an unfinished pre-training from {workdir / 'pretrain_metrics.jsonl'}")
    pc = cfg.pretrain
    require_world(cfg.env, "pre-training")
    used = distributed.devices_for(pc.batch_size, devices, what=f"pretrain.batch_size={pc.batch_size} samples")
    env = NavEnv(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    spec = learner(cfg)
    target_rgb, target_seg = targets_of(spec, env)
    key = jax.random.PRNGKey(cfg.seed)
    k_params, k_data, k_order = jax.random.split(key, 3)
    t0 = time.perf_counter()
    data = make_dataset(cfg, env, pc.dataset_size, k_data)
    log(f"dataset: {pc.dataset_size} observations in {env.num_scenes} scene(s) in {time.perf_counter() - t0:.1f} s")

    params = networks.init(k_params)
    optimizer = optax.adam(pc.learning_rate)
    opt_state = optimizer.init(params)

    def loss_fn(params, batch):
        target_feats = networks.target_stream(params, target_rgb)
        conv4, _ = networks.encode(params, batch["rgb"], target_feats[batch["target"]])
        truth = FrameTruth(batch.get("depth_gt"), batch.get("seg_gt"))
        terms = vn_terms(spec, networks, params, conv4, truth, target_seg[batch["target"]])
        return sum(getattr(w, k) * v for k, v in terms.items()), terms

    def step_fn(params, opt_state, batch):
        (loss, terms), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, batch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, dict(terms, total=loss)

    place = lambda batch: batch  # noqa: E731
    step = jax.jit(step_fn)
    if len(used) > 1:  # each batch split over the devices, the rest replicated; XLA reduces the gradients
        mesh = jax.sharding.Mesh(np.array(used), ("batch",))
        split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        whole = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
        params, opt_state = jax.device_put((params, opt_state), whole)
        place = lambda batch: jax.device_put(batch, split)  # noqa: E731
        step = jax.jit(step_fn, in_shardings=(whole, whole, split), out_shardings=(whole, whole, whole))
        log(f"each batch of {pc.batch_size} is split over {len(used)} {used[0].platform} devices")

    writer = MetricsWriter(workdir, tensorboard=False, name="pretrain_metrics", note=lambda: "nothing was saved")
    try:
        save_config(cfg, workdir / "config.yaml")
    except OSError as e:
        raise PretrainError(f"cannot write {workdir / 'config.yaml'}: {io_reason(e)}") from None
    n = pc.dataset_size
    batches = max(1, n // pc.batch_size)
    rng = np.random.default_rng(int(jax.random.randint(k_order, (), 0, 2**31 - 1)))
    try:
        for epoch in range(1, pc.epochs + 1):
            order = rng.permutation(n)
            sums, t0 = {}, time.perf_counter()
            for b in range(batches):
                idx = order[b * pc.batch_size : (b + 1) * pc.batch_size]
                params, opt_state, terms = step(params, opt_state, place({k: v[idx] for k, v in data.items()}))
                for k, v in terms.items():
                    sums[k] = sums.get(k, 0.0) + v
            row = {"epoch": epoch, **{f"loss/{k}": float(v) / batches for k, v in sums.items()},
                   "seconds": time.perf_counter() - t0}
            if not np.isfinite(row["loss/total"]):
                raise PretrainError(f"non-finite loss in epoch {epoch}; nothing was saved")
            writer.write(row)
            log(f"epoch {epoch}/{pc.epochs}: " + ", ".join(f"{k[5:]} {v:.4f}" for k, v in row.items() if k.startswith("loss/")))
    finally:
        writer.close()
    trained = {"params": {k: v for k, v in params["params"].items() if k in TRAINED_LAYERS}}
    quiet_abandoned_io()
    try:
        with ocp.StandardCheckpointer() as checkpointer:
            checkpointer.save((workdir / PRETRAINED_DIR).absolute(), trained)
    except Exception as e:  # noqa: BLE001 - orbax and tensorstore raise many kinds
        for partial in workdir.glob(f"{PRETRAINED_DIR}{PARTIAL}*"):
            shutil.rmtree(partial, ignore_errors=True)
        raise PretrainError(f"cannot write the pre-trained parameters to {workdir / PRETRAINED_DIR}: {io_reason(e)}; "
                            f"nothing was saved") from None
    log(f"wrote the parameters of {', '.join(trained['params'])} to {workdir / PRETRAINED_DIR}")
    return params


def load_matching(params, pretrained_dir):
    """`params` with every array whose path and shape match one in the pre-trained
    checkpoint of `pretrained_dir` (a pretrain work directory) replaced by it.

    Returns (params, loaded paths, kept paths)."""
    path = Path(pretrained_dir) / PRETRAINED_DIR
    if not path.is_dir():
        raise PretrainError(f"{pretrained_dir}: no pre-trained parameters (missing {PRETRAINED_DIR}/)")
    silence_abandoned_reads()
    try:
        with ocp.StandardCheckpointer() as checkpointer:
            saved = checkpointer.restore(path.absolute())
    except Exception as e:  # noqa: BLE001 - orbax raises many kinds
        raise PretrainError(f"{path}: cannot read the pre-trained parameters ({type(e).__name__})") from None
    flat_saved = {jax.tree_util.keystr(p): v for p, v in jax.tree_util.tree_leaves_with_path(saved)}
    loaded, kept = [], []

    def pick(p, x):
        name = jax.tree_util.keystr(p)
        v = flat_saved.get(name)
        if v is not None and np.shape(v) == x.shape:
            loaded.append(name)
            return jax.numpy.asarray(v, x.dtype)
        kept.append(name)
        return x

    return jax.tree_util.tree_map_with_path(pick, params), loaded, kept
