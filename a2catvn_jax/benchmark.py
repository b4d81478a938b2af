"""Throughput benchmarks.

    python -m a2catvn_jax.benchmark env [--batch-sizes 16 64 256 1024] [--resolutions 64 84 174]
    python -m a2catvn_jax.benchmark render [--batch-sizes 64] [--resolutions 64 84 174]
        [--renderers raycast mjx warp] [--cores 1]
    python -m a2catvn_jax.benchmark train [--configs quickstart paper] [--updates 5]
        [--processes 1 2 | --batch-sizes 16 256 1024 4096]
    python -m a2catvn_jax.benchmark compile [--configs quickstart] [--batch-sizes 16 256 1024 4096]
    python -m a2catvn_jax.benchmark loop [--configs quickstart] [--updates 20] [--per-call 10 25]
        [--houses-argument]
    python -m a2catvn_jax.benchmark network [--resolution 84] [--frames 320] [--targets 16]
        [--networks default configs/presets/authors_network.yaml] [--conv-impls xla auto matmul | --layers]
    python -m a2catvn_jax.benchmark profile [--configs quickstart image_goals_cpu paper] [--updates 5]
        [--networks default configs/presets/authors_network.yaml] [--ops 15]

`env`: frames/s of `NavEnv.step` (one frame = one agent step with its RGB, depth and
segmentation rendered) in a multi-room house, for each batch size and resolution,
with compile times; and, for the same house MJCF at the same resolution, MuJoCo's own
OpenGL renderer (`mujoco.Renderer`, RGB + depth + segmentation passes) at the same
agent poses, and the ratio of the two.

`render`: frames/s of rendering alone (RGB, depth and segmentation, no environment
step around it) on the same house from the same camera poses, for each batch size and
resolution: the ray caster, `mjx.render` (impl warp) and MuJoCo Warp's renderer called
directly; each in its own process pinned to `--cores` CPU cores (default 1: frames/s
per core), with the share of pixels whose geom id agrees with the ray caster's
(`bench/render_speed.py`).

`train`: frames/s of the training update (rollout, replay, every loss, optimiser step)
for `configs/quickstart.yaml` and `configs/paper.yaml` (Table I: 16 environments,
20-step rollouts, every auxiliary task, 4 houses of 2x2 rooms) at `--paper-resolution`
pixels, with compile time and the share of the time spent in the environment (a
rollout of random actions timed alone). With `--processes N ...`: for each N, N copies
of that benchmark at once, each a process pinned to its share of the CPU cores
(`study/workers.py`, what `experiments --jobs N` does), and the frames/s
of all of them together: whether independent runs finish sooner side by side. With
`--batch-sizes B ...`: each configuration at each number of environments B, one process
per size, with the memory it needs: the training state (parameters, optimiser,
environments, replay), XLA's buffers for one update, and the process's peak resident
memory.

`network`: forward+backward frames/s of the conv base with the depth and segmentation
heads on `--frames` (observation, target) pairs: as the update runs it (the target
stream once per distinct target), with both streams computed for every frame, and
the same network in PyTorch (`pip install torch==2.13.0`), timed in turns, with the
ratios. With `--networks`, each listed network in turn: `default` (the built-in one) or
a config file of agent keys such as `configs/presets/authors_network.yaml`.
With `--conv-impls`, instead, each network with each `agent.conv_impl` listed, timed
in turns in one process (`--repeats` rounds), so that the ratios come from one run.
With `--layers`, instead, the image stream's conv1 and conv2 alone, forward+backward
on `--frames` images, by XLA's convolution, by matrix products and in PyTorch, timed
in turns: where the network's time against PyTorch's goes.

`compile`: what compiling the training update costs at each of `--batch-sizes`
(default 16 256 1024 4096) for each of `--configs`, on the abstract training state
(nothing allocated, nothing run): building the environment and the update, tracing and
lowering, XLA's compile, the compiled program's size and XLA's buffers for one update.

`loop`: training frames/s as the host drives the update, timed in turns in one process:
one update per call with its metrics read back before the next, against `--per-call K`
updates per call of the device loop (`train.updates_per_call`), `--updates` updates per
setting and round, the median of `--repeats` rounds. With `--houses-argument`, also one
update per call compiled with the houses' arrays as an argument, as
`train.new_houses_every` runs it, against the same update with them compiled in.

`profile`: milliseconds per update of each phase of the training update (rollout and
the environment alone; the loss forward and forward + backward for plain A2C and for
each auxiliary term on top of it; the optimiser; the whole update), for each
configuration of `configs/` named by `--configs` (`paper` at `--paper-resolution`)
with each network of `--networks`, and the share of a dense matrix product's
floating-point rate (timed in the same run) that the update reaches; with `--ops N`,
the N XLA operations of the update that take the most time, with the program source
each comes from (`bench/profile.py`).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from a2catvn_jax import cli
from a2catvn_jax.bench import render_speed
from a2catvn_jax.bench.profile import matmul_gflops, profile_update
from a2catvn_jax.bench.throughput import (
    bench_compile,
    bench_conv_impls,
    bench_env,
    bench_loop,
    bench_mujoco_gl,
    bench_network,
    bench_stream_layers,
    bench_train,
)
from a2catvn_jax.config import CONFIGS, load_config
from a2catvn_jax.env import mjx_render
from a2catvn_jax.study import workers

CONFIG_NAMES = sorted(p.stem for p in CONFIGS.glob("*.yaml") if p.stem != "default")


def _header():
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, {jax.devices()[0].device_kind}, "
          f"jax {jax.__version__}, {time.strftime('%Y-%m-%d')}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.benchmark", description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=["env", "render", "train", "compile", "loop", "network", "profile"], help="what to benchmark")
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=None, metavar="B",
                        help="env (default: 16 64 256 1024); render (default: 64); "
                             "train: one process per size, with its peak memory; compile (default: 16 256 1024 4096)")
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 84, 174], help="env, render")
    parser.add_argument("--renderers", nargs="+", choices=list(render_speed.RENDERERS), default=list(render_speed.RENDERERS),
                        help="render: raycast (ours), mjx (mjx.render inside jit), warp (MuJoCo Warp called directly)")
    parser.add_argument("--cores", type=int, default=1, help="render: CPU cores each renderer's process is pinned to")
    parser.add_argument("--steps", type=int, default=5, help="env: timed steps per setting")
    parser.add_argument("--gl-frames", type=int, default=200, help="env: frames timed for MuJoCo's renderer")
    parser.add_argument("--no-gl", action="store_true", help="env: skip MuJoCo's OpenGL renderer")
    parser.add_argument("--backends", nargs="+", choices=["raycast", "mjx"], default=["raycast", "mjx"],
                        help="env: render backends, side by side")
    parser.add_argument("--max-pixels", type=float, default=3.2e7, help="env: skip settings with more batch*pixels")
    parser.add_argument("--configs", nargs="+", choices=CONFIG_NAMES, default=["quickstart", "paper"],
                        help="train, profile: configurations of configs/")
    parser.add_argument("--updates", type=int, default=5, help="train, profile: timed updates (calls) per configuration")
    parser.add_argument("--ops", type=int, default=0, metavar="N",
                        help="profile: also list the N XLA operations of the update that take the most time")
    parser.add_argument("--processes", type=int, nargs="+", default=None, metavar="N",
                        help="train: for each N, N copies of the benchmark at once, each on its share of the cores")
    parser.add_argument("--paper-resolution", type=int, default=84,
                        help="train, profile: image size of the paper-sized config")
    parser.add_argument("--resolution", type=int, default=84, help="network: image size")
    parser.add_argument("--frames", type=int, default=320, help="network: (observation, target) pairs per pass")
    parser.add_argument("--targets", type=int, default=16, help="network: distinct targets among them")
    parser.add_argument("--repeats", type=int, default=5, help="network: timed passes; render: timed rounds")
    parser.add_argument("--conv-impls", nargs="+", choices=["auto", "xla", "matmul"],
                        help="network: compare these agent.conv_impl values, timed in turns")
    parser.add_argument("--layers", action="store_true",
                        help="network: time the image stream's conv1 and conv2 alone, each way and in PyTorch")
    parser.add_argument("--networks", nargs="+", metavar="NET", default=["default"],
                        help="network, profile: the networks to time, side by side: default (the built-in network) or config "
                             "files of agent keys, e.g. --networks default configs/presets/authors_network.yaml")
    cli.add_config_args(parser, config=False, help="configuration changes applied to every benchmarked setting")
    parser.add_argument("--per-call", type=int, nargs="*", default=[10, 25], metavar="K",
                        help="loop: updates per call of the device loop to time against one update per call")
    parser.add_argument("--houses-argument", action="store_true",
                        help="loop: also time one update per call compiled with the houses as an argument "
                             "(as train.new_houses_every runs it)")
    parser.add_argument("--json", help="also write the results to this JSON file")
    args = parser.parse_args(argv)
    if args.what == "train" and args.processes and args.batch_sizes:
        parser.error("train: give --processes or --batch-sizes, not both")
    overrides = cli.overrides_of(args)
    if args.what == "loop" and any(k < 1 for k in args.per_call):
        parser.error(f"loop: --per-call {' '.join(str(k) for k in args.per_call if k < 1)}: must be >= 1")
    if args.what == "render":
        if overrides:
            parser.error("render: --set is not used (every renderer draws the benchmark's house)")
        small = [f"{name} {v}" for name, values in (("--batch-sizes", args.batch_sizes or []),
                                                    ("--resolutions", args.resolutions), ("--repeats", [args.repeats]))
                 for v in values if v < 1]
        if small:
            parser.error(f"render: {', '.join(small)}: must be >= 1")
    _header()
    with cli.errors(parser, code=1):
        if args.what == "train" and args.processes:
            rows = _train_processes_table(args, overrides)
        elif args.what == "train" and args.batch_sizes:
            rows = _train_batch_table(args, overrides)
        elif args.what == "train":
            rows = []
            print(f"{'config':>10} {'batch':>6} {'res':>5} {'train fps':>10} {'compile s':>10} {'env fps':>9} {'env share':>10}")
            for name in args.configs:
                extra = [f"env.render.image_size={args.paper_resolution}"] if name == "paper" else []
                r = bench_train(name, extra + overrides, args.updates)
                rows.append(r)
                print(f"{name:>10} {r['batch']:>6} {r['resolution']:>5} {r['train_fps']:10.0f} {r['compile_s']:10.1f} "
                      f"{r['env_fps']:9.0f} {r['env_share']:10.0%}", flush=True)
        elif args.what == "compile":
            rows = []
            print(f"{'config':>10} {'batch':>6} {'res':>5} {'build s':>8} {'trace s':>8} {'compile s':>10} "
                  f"{'HLO ops':>8} {'update GiB':>11}")
            for name in args.configs:
                extra = [f"env.render.image_size={args.paper_resolution}"] if name == "paper" else []
                for batch in args.batch_sizes or (16, 256, 1024, 4096):
                    r = bench_compile(name, [*extra, *overrides, f"env.num_envs={batch}"])
                    rows.append(r)
                    print(f"{name:>10} {r['batch']:>6} {r['resolution']:>5} {r['build_s']:8.1f} {r['trace_s']:8.1f} "
                          f"{r['compile_s']:10.1f} {r['hlo_ops']:8d} {r['update_gib']:11.2f}", flush=True)
        elif args.what == "loop":
            rows = []
            for name in args.configs:
                extra = [f"env.render.image_size={args.paper_resolution}"] if name == "paper" else []
                r = bench_loop(name, extra + overrides, args.updates, tuple(args.per_call), args.repeats,
                               args.houses_argument)
                rows.append(r)
                print(f"{name} (batch {r['batch']}), training frames/s, median of {r['rounds']} rounds of "
                      f"{r['updates']} updates each, in turns: "
                      + ", ".join(f"{label} {fps:.0f}" for label, fps in r["fps"].items()), flush=True)
        elif args.what == "profile":
            rows = _profile_table(args, overrides)
        elif args.what == "render":
            rows = _render_table(args, overrides)
        elif args.what == "network" and args.layers:
            rows = []
            for name in args.networks:
                layers = bench_stream_layers(args.resolution, args.frames, args.repeats, overrides,
                                             config=None if name == "default" else name)
                rows.append({"network": name, "resolution": args.resolution, "frames": args.frames, "layers": layers})
                print(f"{name}: the image stream's layers, forward+backward on {args.frames} images, ms (median of "
                      f"{args.repeats} rounds):")
                for layer, r in layers.items():
                    torch_ms = f"{r['torch']:.1f}" if "torch" in r else "not installed"
                    print(f"  {layer} ({r['shape']}): XLA convolution {r['xla']:.1f}, matrix products {r['matmul']:.1f} "
                          f"(auto takes {r['auto']}), PyTorch {torch_ms}", flush=True)
        elif args.what == "network" and args.conv_impls:
            rows = []
            for name in args.networks:
                fps = bench_conv_impls(args.resolution, args.frames, args.targets, args.repeats, args.conv_impls,
                                       overrides, config=None if name == "default" else name)
                rows.append({"network": name, "resolution": args.resolution, "frames": args.frames, "fps": fps})
                print(f"{name}: forward+backward as trained, {args.frames} frames at {args.resolution}x{args.resolution}, "
                      f"frames/s (median of {args.repeats} rounds): "
                      + ", ".join(f"conv_impl={impl} {v:.0f}" for impl, v in fps.items()), flush=True)
        elif args.what == "network":
            rows = []
            for name in args.networks:
                default = name == "default"
                r = bench_network(args.resolution, args.frames, args.targets, args.repeats, overrides,
                                  config=None if default else name)
                rows.append({"network": name, **r})
                print(f"{name}: {r['params']:,} parameters in the whole network; forward+backward, {args.frames} frames at "
                      f"{args.resolution}x{args.resolution}, frames/s:")
                print(f"  JAX, target stream once per distinct target ({args.targets}): {r['jax_fps']:.0f}")
                print(f"  JAX, both streams every frame:                      {r['jax_per_frame_fps']:.0f}")
                if r["torch_fps"] is None:
                    print("  PyTorch: not installed (pip install torch==2.13.0)")
                else:
                    print(f"  PyTorch {__import__('torch').__version__}, both streams every frame:      {r['torch_fps']:.0f}")
                    print(f"  ratio JAX as trained / PyTorch: {r['jax_fps'] / r['torch_fps']:.2f}; "
                          f"like for like: {r['jax_per_frame_fps'] / r['torch_fps']:.2f}")
        else:
            rows = _bench_env_table(args, overrides)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(rows, f, indent=1)


def _train_children(args, name: str, overrides, settings: list, jobs: int, tmp: str, tag: str) -> list:
    """`benchmark train --configs NAME` in one process per entry of `settings` (extra
    KEY=VALUE overrides after `overrides`), `jobs` at a time, each pinned to its share of
    the cores: the row each one wrote."""
    out = [Path(tmp) / f"{name}_{tag}_{i}.json" for i in range(len(settings))]
    logs = [p.with_suffix(".log") for p in out]
    commands = [[sys.executable, "-m", "a2catvn_jax.benchmark", "train", "--configs", name, "--updates", str(args.updates),
                 "--paper-resolution", str(args.paper_resolution), "--json", str(path),
                 *(["--set", *overrides, *extra] if overrides or extra else [])]
                for path, extra in zip(out, settings)]
    codes = workers.run_pool(commands, jobs, logs)
    if any(codes):
        i = next(i for i, c in enumerate(codes) if c)
        if codes[i] < 0:  # run_pool gives -N for a process killed by signal N
            oom = " (the kernel's out-of-memory killer sends it)" if codes[i] == -9 else ""
            raise workers.WorkerError(f"a benchmark process was killed by signal {-codes[i]}{oom}: "
                                      f"{' '.join(commands[i][3:])}")
        raise workers.WorkerError(f"a benchmark process failed (exit status {codes[i]}): {workers.last_line(logs[i])}")
    return [json.loads(p.read_text())[0] for p in out]


def _train_batch_table(args, overrides) -> list:
    """`train` at each batch size of `--batch-sizes`, one process each (one at a time, on
    every core), so that each size's peak memory is its own."""
    rows = []
    print(f"{'config':>10} {'batch':>6} {'res':>5} {'train fps':>10} {'init s':>7} {'compile s':>10} {'first s':>8} "
          f"{'state GiB':>10} {'update GiB':>11} {'peak GiB':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.configs:
            for batch in args.batch_sizes:
                (r,) = _train_children(args, name, overrides, [[f"env.num_envs={batch}"]], 1, tmp, f"b{batch}")
                rows.append(r)
                update = "-" if r["update_gib"] is None else f"{r['update_gib']:.2f}"
                print(f"{name:>10} {r['batch']:>6} {r['resolution']:>5} {r['train_fps']:10.0f} {r['init_s']:7.1f} "
                      f"{r['compile_s']:10.1f} {r['first_s']:8.1f} {r['state_gib']:10.2f} {update:>11} "
                      f"{r['peak_rss_gib']:9.2f}", flush=True)
    return rows


def _train_processes_table(args, overrides) -> list:
    """`train` in N processes at once for each N of `--processes`: their frames/s and the sum."""
    rows = []
    print(f"{'config':>10} {'processes':>9} {'cores each':>10} {'train fps per process':>34} {'train fps, all':>15}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.configs:
            for n in args.processes:
                groups = workers.core_groups(n)
                fps = [r["train_fps"] for r in _train_children(args, name, overrides, [[]] * n, n, tmp, f"p{n}")]
                cores = "/".join(str(len(g)) for g in groups)
                rows.append({"config": name, "processes": n, "cores": [len(g) for g in groups], "train_fps": fps,
                             "train_fps_total": sum(fps)})
                print(f"{name:>10} {n:>9} {cores:>10} {', '.join(f'{f:.0f}' for f in fps):>34} {sum(fps):15.0f}",
                      flush=True)
    return rows


def _profile_table(args, overrides) -> list:
    settings = []  # every configuration loaded (and checked) before anything is timed
    for name in args.configs:
        extra = [f"env.render.image_size={args.paper_resolution}"] if name == "paper" else []
        for network in args.networks:
            files = [CONFIGS / f"{name}.yaml"] + ([] if network == "default" else [network])
            settings.append((name, network, load_config(files, extra + overrides)))
    peak = matmul_gflops()
    print(f"dense float32 matrix product (1024x1024): {peak:.1f} GFLOP/s")
    rows = []
    for name, network, cfg in settings:
        r = profile_update(cfg, repeats=args.updates, ops=args.ops)
        rows.append({"config": name, "network": network, "matmul_gflops_per_s": peak, **r})
        print(f"\n{name}, network {network}: batch {r['batch']}, {r['resolution']} px, {r['frames_per_update']} frames "
              f"per update, {r['train_fps']:.0f} frames/s")
        print(f"  {'phase':<62} {'ms/update':>10} {'share':>6}")
        for phase, seconds in r["phases_s"].items():
            print(f"  {phase:<62} {seconds * 1e3:10.1f} {seconds / r['update_s']:6.0%}")
        print(f"  {'whole update':<62} {r['update_s'] * 1e3:10.1f} {1:6.0%}")
        print(f"  {'  sum of rollout, whole loss fwd+bwd and optimiser':<62} {r['sum_of_phases_s'] * 1e3:10.1f} "
              f"{r['sum_of_phases_s'] / r['update_s']:6.0%}")
        bound = " at least" if r["flops_lower_bound"] else ""
        print(f"  {r['update_matmul_flops'] / 1e9:.2f}{bound} GFLOP of matrix products and convolutions per update: "
              f"{r['update_gflops_per_s']:.1f} GFLOP/s, {r['update_gflops_per_s'] / peak:.0%} of the matrix product's "
              "rate", flush=True)
        if "op_times" in r:
            t = r["op_times"]
            print(f"  the {len(t['ops'])} XLA operations that take the most time (of {t['ops_ms_per_update']:.1f} ms per "
                  "update in all operations, under the profiler):")
            print(f"  {'ms/update':>10} {'calls':>6}  {'output':<22} source")
            for op in t["ops"]:
                print(f"  {op['ms_per_update']:10.1f} {op['calls_per_update']:6g}  {op['shape']:<22} "
                      f"{op['source'] or op['op']}")
    return rows


def _render_table(args, overrides) -> list:
    """Rendering alone, each renderer, batch size and resolution in its own process
    pinned to `--cores` cores (`bench/render_speed.py`)."""
    # The ray caster first: the others' geom ids are compared with its.
    renderers = [r for r in render_speed.RENDERERS if r in args.renderers]
    if any(r != "raycast" for r in renderers) and mjx_render.unavailable():
        print(f"# mjx and warp left out: {mjx_render.unavailable()}", file=sys.stderr)
        renderers = [r for r in renderers if r == "raycast"]
    if "raycast" not in renderers:
        print("# raycast not among --renderers: geom ids are not compared", file=sys.stderr)
    cores = workers.available_cores()
    if not 1 <= args.cores <= len(cores):
        raise workers.WorkerError(f"render: --cores must be between 1 and {len(cores)} (the cores this process may use), "
                         f"got {args.cores}")
    cores = cores[-args.cores:]
    print(f"# each renderer in a process pinned to core(s) {','.join(map(str, cores))}")
    print(f"{'batch':>6} {'res':>5} {'geoms':>6} {'renderer':>9} {'frames/s':>9} {'cores':>6} {'per core':>9} "
          f"{'compile s':>10} {'same geom as raycast':>21}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for res in args.resolutions:
            for batch in args.batch_sizes or [64]:
                reference = None
                for renderer in renderers:
                    out = Path(tmp) / f"{renderer}_{batch}_{res}.json"
                    log = out.with_suffix(".log")
                    command = [sys.executable, "-m", "a2catvn_jax.bench.render_speed", renderer, "--batch", str(batch),
                               "--resolution", str(res), "--repeats", str(args.repeats), "--out", str(out)]
                    with open(log, "w") as f:
                        code = subprocess.run(workers.pinned(command, cores), stdout=f, stderr=subprocess.STDOUT,
                                              env=workers.worker_env(cores)).returncode
                    if code:
                        raise workers.WorkerError(f"render: the {renderer} process failed (exit status {code}): "
                                                  f"{workers.last_line(log)}")
                    r = json.loads(out.read_text())
                    geom = np.load(str(out) + ".npy")
                    if renderer == "raycast":
                        reference = geom
                    compared = renderer != "raycast" and reference is not None
                    r["same_geom_as_raycast"] = float(np.mean(geom == reference)) if compared else None
                    if r["pinned_cores"] != args.cores:
                        raise workers.WorkerError(f"render: the {renderer} process ran on {r['pinned_cores']} cores, "
                                                  f"not the {args.cores} it was pinned to")
                    r["frames_per_s_per_core"] = r["frames_per_s"] / max(r["cores"], 1e-9)
                    rows.append(r)
                    same = "-" if r["same_geom_as_raycast"] is None else f"{r['same_geom_as_raycast']:.4%}"
                    print(f"{batch:>6} {res:>5} {r['geoms']:>6} {renderer:>9} {r['frames_per_s']:9.0f} {r['cores']:6.2f} "
                          f"{r['frames_per_s_per_core']:9.0f} {r['compile_s']:10.1f} {same:>21}", flush=True)
    return rows


def _bench_env_table(args, overrides) -> list:
    """Environment steps (move + render) per second for each resolution, batch size and
    render backend, in one run on one house at the same poses (the backends step the
    same episodes), beside MuJoCo's OpenGL renderer on those poses. `cores`: CPU time
    over wall time while the steps ran (the threads the backend kept busy)."""
    rows = []
    gl_cache = {}
    backends = [b for b in args.backends if b != "mjx" or not mjx_render.unavailable()]
    if backends != args.backends:
        print(f"# backend mjx left out: {mjx_render.unavailable()}", file=sys.stderr)
    print(f"{'batch':>6} {'res':>5} {'geoms':>6} {'backend':>8} {'env fps':>9} {'cores':>6} {'compile s':>10} "
          f"{'GL fps':>8} {'/ GL':>6}")
    for res in args.resolutions:
        for batch in args.batch_sizes or [16, 64, 256, 1024]:
            if batch * res * res > args.max_pixels:
                print(f"{batch:>6} {res:>5}  skipped (batch*pixels > --max-pixels)")
                continue
            for backend in backends:
                r = bench_env(batch, res, args.steps, [*overrides, f"env.render.backend={backend}"])
                env = r.pop("env")
                poses = r.pop("poses")
                if not args.no_gl and res not in gl_cache:
                    try:
                        gl_cache[res] = bench_mujoco_gl(env, res, poses, args.gl_frames)
                    except RuntimeError as e:
                        print(f"# MuJoCo OpenGL renderer unavailable: {e}", file=sys.stderr)
                        gl_cache[res] = None
                gl = gl_cache.get(res)
                r.update(backend=backend, mujoco_gl_fps=gl, ratio=r["frames_per_s"] / gl if gl else None)
                rows.append(r)
                gl_s = f"{gl:8.0f}" if gl else f"{'-':>8}"
                ratio_s = f"{r['ratio']:6.2f}" if gl else f"{'-':>6}"
                print(f"{batch:>6} {res:>5} {r['geoms']:>6} {backend:>8} {r['frames_per_s']:9.0f} {r['cores']:6.2f} "
                      f"{r['compile_s']:10.1f} {gl_s} {ratio_s}", flush=True)
                del env
    return rows


if __name__ == "__main__":
    main()
