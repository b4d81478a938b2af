"""Throughput of the environment, the training update and the network (see `python -m a2catvn_jax.benchmark`)."""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from a2catvn_jax.agent.layers import auto_impl, conv2d
from a2catvn_jax.agent.networks import Conv1, make_networks, num_params
from a2catvn_jax.agent.update import NONFINITE, frames_per_update, make_update, repeated
from a2catvn_jax.config import CONFIGS, load_config
from a2catvn_jax.env import NavEnv
from a2catvn_jax.run.training import check_renewable


def env_config(batch: int, resolution: int, overrides):
    return load_config(
        None,
        [
            f"env.num_envs={batch}",
            f"env.render.image_size={resolution}",
            "env.scene.kind=house",
            "env.scene.grid=[2,3]",
            "env.scene.num_scenes=1",
            "env.goals_per_scene=4",
            *overrides,
        ],
    ).env


def bench_env(batch: int, resolution: int, steps: int, overrides=(), world=None) -> dict:
    cfg = env_config(batch, resolution, overrides)
    env = NavEnv(cfg, world=world)
    reset = jax.jit(env.reset)
    step = jax.jit(env.step)
    t0 = time.perf_counter()
    state = jax.block_until_ready(reset(jax.random.PRNGKey(0)))
    actions = jax.random.randint(jax.random.PRNGKey(1), (steps + 1, batch), 0, env.num_actions)
    state = jax.block_until_ready(step(state, actions[0]))
    compile_s = time.perf_counter() - t0
    poses, fallbacks = [], 0
    t0, c0 = time.perf_counter(), time.process_time()
    for k in range(steps):
        state = step(state, actions[k + 1])
        if k < 4:
            poses.append(np.asarray(state.info.pose))
    jax.block_until_ready(state)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    fallbacks = int(np.asarray(state.metrics["fallback"]).sum())
    return {
        "batch": batch,
        "resolution": resolution,
        "frames_per_s": batch * steps / dt,
        "cores": cpu / dt,
        "compile_s": compile_s,
        "geoms": int(env.world.models[0].ngeom),
        "fallback_frames_last_step": fallbacks,
        "poses": np.concatenate(poses),
        "env": env,
    }


def bench_mujoco_gl(env, resolution: int, poses: np.ndarray, frames: int) -> float:
    from a2catvn_jax.bench import mujoco_gl  # needs a headless OpenGL

    return mujoco_gl.benchmark_fps(
        env.scene_mjcf(0), resolution, resolution, n_frames=frames, poses=poses, cam_height=env.cfg.camera_height
    )


def _gib(n_bytes) -> float:
    return n_bytes / 2**30


def _timed_updates(cfg, env, updates: int):
    """(seconds, frames/s, memory, the environments' state after the last update) of the
    training update. Seconds: `init_s` (compiling and running `init`: parameters, the
    environments' reset, the replay), `compile_s` (lowering and compiling the update, XLA
    only) and `first_s` (its first call, which runs one update). Memory in GiB:
    `state` (the training state: parameters, optimiser, environments, replay), `update`
    (XLA's buffers for one update beyond its donated argument, from the compiled
    program), and the process's peak resident memory so far."""
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    t0 = time.perf_counter()
    state = jax.block_until_ready(init(jax.random.PRNGKey(0)))
    t1 = time.perf_counter()
    compiled = update.lower(state).compile()
    t2 = time.perf_counter()
    stats = compiled.memory_analysis()
    state, m = compiled(state)
    jax.block_until_ready(m)
    seconds = {"init_s": t1 - t0, "compile_s": t2 - t1, "first_s": time.perf_counter() - t2}
    t0 = time.perf_counter()
    for _ in range(updates):
        state, m = compiled(state)
    jax.block_until_ready(m)
    fps = updates * frames_per_update(cfg) / (time.perf_counter() - t0)
    memory = {"state_gib": _gib(sum(x.nbytes for x in jax.tree_util.tree_leaves(state))),
              "update_gib": None if stats is None else _gib(stats.temp_size_in_bytes + stats.output_size_in_bytes
                                                            - stats.alias_size_in_bytes),
              "peak_rss_gib": _gib(peak_rss_bytes())}
    return seconds, fps, memory, state.env_state


def peak_rss_bytes() -> int:
    """This process's peak resident memory (Linux and macOS)."""
    import resource
    import sys

    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024


def random_steps(env, steps: int):
    """A jitted `(env_state, key) -> env_state`: `steps` environment steps with uniformly
    random actions, in one scan."""

    @jax.jit
    def rollout(state, key):
        def body(s, k):
            return env.step(s, jax.random.randint(k, (env.num_envs,), 0, env.num_actions)), None

        return jax.lax.scan(body, state, jax.random.split(key, steps))[0]

    return rollout


def _env_rollout_fps(env, state, steps: int, repeats: int) -> float:
    """Frames/s of `steps` environment steps with random actions, in one jitted scan, from
    the environments' `state` (the training's: no reset to compile)."""
    rollout = random_steps(env, steps)
    state = rollout(state, jax.random.PRNGKey(1))
    jax.block_until_ready(state)
    t0 = time.perf_counter()
    for k in range(repeats):
        state = rollout(state, jax.random.PRNGKey(k + 2))
    jax.block_until_ready(state)
    return repeats * steps * env.num_envs / (time.perf_counter() - t0)


def bench_train(name: str, overrides, updates: int) -> dict:
    cfg = load_config(CONFIGS / f"{name}.yaml", overrides)
    env = NavEnv(cfg.env)
    seconds, fps, memory, env_state = _timed_updates(cfg, env, updates)
    env_fps = _env_rollout_fps(env, env_state, cfg.train.rollout_length, max(2, updates))
    return {"config": name, "batch": env.num_envs, "resolution": cfg.env.render.image_size, "train_fps": fps,
            **seconds, "env_fps": env_fps, "env_share": fps / env_fps, **memory}


def bench_compile(name: str, overrides) -> dict:
    """What compiling the training update of `configs/NAME.yaml` (with `overrides`) costs,
    without allocating the training state: `build_s` (the environment and the update's
    Python objects), `trace_s` (tracing and lowering on the abstract state,
    `jax.eval_shape(init)`), `compile_s` (XLA's compile of the lowered program), the
    size of the program XLA compiled (`hlo_ops`, instructions of the optimised module)
    and XLA's buffers for one update beyond its donated argument (`update_gib`)."""
    cfg = load_config(CONFIGS / f"{name}.yaml", overrides)
    t0 = time.perf_counter()
    env = NavEnv(cfg.env)
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    t1 = time.perf_counter()
    lowered = update.lower(jax.eval_shape(init, jax.random.PRNGKey(0)))
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    stats = compiled.memory_analysis()
    text = compiled.as_text() or ""
    return {"config": name, "batch": env.num_envs, "resolution": cfg.env.render.image_size,
            "build_s": t1 - t0, "trace_s": t2 - t1, "compile_s": t3 - t2,
            "hlo_ops": sum(1 for line in text.splitlines() if " = " in line),
            "update_gib": None if stats is None else _gib(stats.temp_size_in_bytes + stats.output_size_in_bytes
                                                          - stats.alias_size_in_bytes)}


def _network_pass(resolution: int, frames: int, overrides=(), config=None):
    """What `benchmark network` times: (parameters, the jitted gradient of a loss on the
    conv base's features and the VN heads' outputs, observations [frames], target images
    [frames]); the gradient takes (params, observations, targets, target index per frame)."""
    net = make_networks(load_config(config, [f"env.render.image_size={resolution}", *overrides]), 8)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    rgb = jax.random.randint(k1, (frames, resolution, resolution, 3), 0, 256).astype(jnp.uint8)
    target_rgb = jax.random.randint(k2, (frames, resolution, resolution, 3), 0, 256).astype(jnp.uint8)

    def loss(params, rgb, target_rgb, target_index):
        target_feats = net.target_stream(params, target_rgb)
        conv4, feats = net.encode(params, rgb, target_feats[target_index])
        heads = net.vn_heads(params, conv4)
        return jnp.mean(feats**2) + sum(jnp.mean(h**2) for h in heads.values())

    return net.init(k3), jax.jit(jax.grad(loss)), rgb, target_rgb


def _median_seconds(steps: dict, rounds: int) -> dict:
    """{name: median seconds of one call} of the callables `steps`, each called once to
    compile or warm up, then timed in turns, one call of each per round, for `rounds`
    rounds (so a slow spell of a shared machine slows all of them)."""
    for step in steps.values():
        jax.block_until_ready(step())
    times = {name: [] for name in steps}
    for _ in range(rounds):
        for name, step in steps.items():
            t0 = time.perf_counter()
            jax.block_until_ready(step())
            times[name].append(time.perf_counter() - t0)
    return {name: float(np.median(t)) for name, t in times.items()}


def bench_conv_impls(resolution: int, frames: int, targets: int, rounds: int, impls, overrides=(), config=None) -> dict:
    """Forward+backward frames/s of the network as the update runs it (see
    `bench_network`) with each `agent.conv_impl` of `impls`, compiled first and then
    timed in turns, one pass of each per round, so that a slow spell of a shared machine
    slows all of them: {impl: median frames/s over the rounds}."""
    steps = {}
    for impl in impls:
        params, grad, rgb, target_rgb = _network_pass(resolution, frames, [*overrides, f"agent.conv_impl={impl}"], config)
        steps[impl] = functools.partial(grad, params, rgb, target_rgb[:targets], jnp.arange(frames) % targets)
    return {impl: frames / seconds for impl, seconds in _median_seconds(steps, rounds).items()}


def bench_network(resolution: int, frames: int, targets: int, repeats: int, overrides=(), config=None,
                  torch: bool = True) -> dict:
    """Forward+backward frames/s of the conv base and VN heads: JAX as trained, JAX with
    both streams per frame, and the same network in PyTorch (`bench.torch_reference`;
    None when torch is not installed or `torch` is False). The three are timed in turns,
    one pass of each per round for `repeats` rounds, and each figure is the median
    round, so a slow spell of a shared machine slows all three. `config` (config files,
    e.g. a preset of agent keys) and `overrides` may set `agent.*` keys (e.g.
    agent.space_to_depth=true)."""
    params, grad, rgb, target_rgb = _network_pass(resolution, frames, overrides, config)
    steps = {
        "jax_fps": functools.partial(grad, params, rgb, target_rgb[:targets], jnp.arange(frames) % targets),
        "jax_per_frame_fps": functools.partial(grad, params, rgb, target_rgb, jnp.arange(frames)),
    }
    try:
        if not torch:
            raise ImportError
        from a2catvn_jax.bench import torch_reference  # needs PyTorch
    except ImportError:
        pass
    else:
        cfg = load_config(config, [f"env.render.image_size={resolution}", *overrides])
        steps["torch_fps"] = torch_reference.step_fn(cfg, frames)
    fps = {name: frames / seconds for name, seconds in _median_seconds(steps, repeats).items()}
    return {"resolution": resolution, "frames": frames, "targets": targets, "params": num_params(params),
            "jax_fps": fps["jax_fps"], "jax_per_frame_fps": fps["jax_per_frame_fps"], "torch_fps": fps.get("torch_fps")}


def bench_stream_layers(resolution: int, frames: int, rounds: int, overrides=(), config=None) -> dict:
    """Forward+backward milliseconds of each conv layer of the network's image stream
    (`networks.Conv1` on uint8 images, as the network runs it; conv2 on conv1's map; a
    ReLU and the mean square as the loss; the kernel's gradient, and conv2's input
    gradient) on `frames` images: by XLA's convolution, by matrix products, and by
    PyTorch's `nn.Conv2d` (NCHW, the image scaled to [0, 1] first, the same padding;
    when torch is installed), timed in turns for `rounds` rounds, medians. {layer:
    {"xla": ms, "matmul": ms, "torch": ms, "auto": the impl agent.conv_impl auto takes,
    "shape": text}}."""
    agent = load_config(config, [f"env.render.image_size={resolution}", *overrides]).agent
    sizes, padding = agent.conv_sizes(resolution), agent.conv_padding
    channels = (3, *agent.conv_channels)
    try:
        import torch
        import torch.nn.functional as F
    except ImportError:
        torch = None
    out = {}
    for i in range(2):
        n, c, f = sizes[i], channels[i], channels[i + 1]
        k, s = agent.conv_kernels[i], agent.conv_strides[i]
        key = jax.random.PRNGKey(i)
        steps = {}
        for impl in ("xla", "matmul"):
            if i == 0:
                x = jax.random.randint(key, (frames, n, n, c), 0, 256).astype(jnp.uint8)
                layer = Conv1(f, agent.space_to_depth, k, s, padding, impl=impl)
                params = layer.init(key, x[:1])
                loss = functools.partial(lambda layer, p, x: jnp.mean(jax.nn.relu(layer.apply(p, x)) ** 2), layer)
                steps[impl] = functools.partial(jax.jit(jax.grad(loss)), params, x)
            else:
                x = jax.random.normal(key, (frames, n, n, c))
                w = jax.random.normal(key, (k, k, c, f)) * 0.05
                loss = functools.partial(
                    lambda impl, w, x: jnp.mean(jax.nn.relu(conv2d(x, w, s, padding.upper(), impl)) ** 2), impl)
                steps[impl] = functools.partial(jax.jit(jax.grad(loss, argnums=(0, 1))), w, x)
        if torch is not None:
            from a2catvn_jax.bench.torch_reference import same_padding

            pad = same_padding(i, n, k, s) if padding == "same" else (0, 0)
            conv = torch.nn.Conv2d(c, f, k, stride=s)
            xt = torch.from_numpy(np.array(x)).permute(0, 3, 1, 2).contiguous().requires_grad_(i > 0)

            def torch_step(conv=conv, xt=xt, pad=pad):
                conv.zero_grad(set_to_none=True)
                x = xt.float() / 255.0 if xt.dtype == torch.uint8 else xt
                F.relu(conv(F.pad(x, pad * 2))).square().mean().backward()

            steps["torch"] = torch_step
        seconds = _median_seconds(steps, rounds)
        out[f"conv{i + 1}"] = {"shape": f"{k}x{k}/{s}, {c} -> {f} channels, {n}x{n} input", "auto": auto_impl(s, c),
                               **{name: 1000 * t for name, t in seconds.items()}}
    return out


def bench_loop(name: str, overrides, updates: int, per_call: tuple[int, ...], rounds: int,
               houses_argument: bool = False) -> dict:
    """Training frames/s of the update loop as the host drives it, timed in turns in one
    process on one state: `1 update, host read` calls the compiled update once per update
    and reads its metrics back with a finite check before the next (one update per call,
    as a loop without `train.updates_per_call` does), and `K per call` runs K updates in
    the device loop (`update.repeated`) and reads the summed metrics once per call. With
    `houses_argument`, also `1 update, houses as argument`: the same as the first, but
    the update compiled with the houses' arrays as an argument rather than as constants
    (how `train.new_houses_every` runs it, so that a new set needs no new compile). Each
    round times `updates` updates of every setting; the median round counts."""
    # With the houses as an argument, the configuration a run that renews them has (its
    # checks refuse what such a run refuses); the update itself does not depend on it.
    renewing = ["train.new_houses_every=1"] if houses_argument else []
    cfg = load_config(CONFIGS / f"{name}.yaml", [*overrides, *renewing])
    env = NavEnv(cfg.env)
    if houses_argument:
        check_renewable(env)
    init, update = make_update(env, make_networks(cfg, env.num_actions), cfg)
    state = init(jax.random.PRNGKey(0))
    one = update.lower(state).compile()
    many = repeated(update).lower(state, np.int32(1)).compile() if per_call else None

    def host_read(state, call=one, args=()):
        for _ in range(updates):
            state, m = call(state, *args)
            m = jax.device_get(m)
            assert all(np.isfinite(float(v)) for v in m.values())
        return state

    def looped(k):
        def run(state):
            for done in range(0, updates, k):
                state, m = many(state, np.int32(min(k, updates - done)))
                m = jax.device_get(m)
                assert m[NONFINITE] == 0
            return state
        return run

    settings = {"1 update, host read": host_read, **{f"{k} per call": looped(k) for k in per_call}}
    if houses_argument:
        houses = env.world.arrays
        with_houses = update.lower(state, houses).compile()
        settings["1 update, houses as argument"] = lambda state: host_read(state, with_houses, (houses,))
    state = jax.block_until_ready(host_read(state))  # warm: the first calls of each
    for run in settings.values():
        state = jax.block_until_ready(run(state))
    times = {label: [] for label in settings}
    for _ in range(rounds):
        for label, run in settings.items():
            t0 = time.perf_counter()
            state = jax.block_until_ready(run(state))
            times[label].append(time.perf_counter() - t0)
    frames = updates * frames_per_update(cfg)
    return {"config": name, "batch": env.num_envs, "updates": updates, "rounds": rounds,
            "fps": {label: frames / float(np.median(t)) for label, t in times.items()}}
