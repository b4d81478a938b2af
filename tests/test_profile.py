"""`benchmark profile`: every phase of the update is timed and the parts add up to about
the whole (A2C with one auxiliary term, on the tiny learner, to keep compiles few).
`benchmark train --processes`: the command each process runs and the table of their
frames/s."""

from __future__ import annotations

import itertools
import json
import sys
import types

import jax
import jax.numpy as jnp
import pytest

from a2catvn_jax import benchmark
from a2catvn_jax.bench import profile as benchmark_profile
from a2catvn_jax.bench import throughput
from a2catvn_jax.bench.profile import AUX_TERMS, matmul_flops, profile_update
from a2catvn_jax.config import load_config
from a2catvn_jax.study import workers
from tiny import TINY_LEARNER

ONLY_DEPTH = [f"train.loss_weights.{t}=0" for t in AUX_TERMS if t != "depth"]


def test_profile_times_every_phase_of_the_update():
    cfg = load_config(None, TINY_LEARNER + ["env.scene.kind=room", "env.scene.num_scenes=1"] + ONLY_DEPTH)
    r = profile_update(cfg, repeats=2, ops=4)
    assert list(r["phases_s"]) == [
        "rollout (environment + policy)", "  of which the environment alone",
        "loss: A2C (actor, critic, entropy), forward", "loss: A2C (actor, critic, entropy), forward + backward",
        "loss: + depth, forward + backward", "loss: every term, forward", "loss: every term, forward + backward",
        "optimiser (clip + RMSprop)",
    ]
    phases = r["phases_s"]
    assert all(phases[k] > 0 for k in phases if not k.startswith("loss: +"))
    assert r["frames_per_update"] == 4 * 4 and r["train_fps"] == r["frames_per_update"] / r["update_s"]
    assert r["sum_of_phases_s"] == (phases["rollout (environment + policy)"] + phases["optimiser (clip + RMSprop)"]
                                    + phases["loss: every term, forward + backward"])
    assert r["update_matmul_flops"] > 0 and r["update_gflops_per_s"] > 0 and not r["flops_lower_bound"]
    ops = r["op_times"]["ops"]
    assert len(ops) == 4 and all(op["ms_per_update"] > 0 and op["calls_per_update"] > 0 for op in ops)
    assert [op["ms_per_update"] for op in ops] == sorted((op["ms_per_update"] for op in ops), reverse=True)
    assert r["op_times"]["ops_ms_per_update"] >= sum(op["ms_per_update"] for op in ops)
    assert all(op["source"] and op["shape"] for op in ops)


def test_hlo_ops_names_each_instruction_by_its_source():
    text = """HloModule m

%fused_computation.1 (p0: f32[2,3], p1: f32[3,4]) -> f32[2,4] {
  %p0 = f32[2,3]{1,0} parameter(0)
  %p1 = f32[3,4]{1,0} parameter(1)
  ROOT %dot.1 = f32[2,4]{1,0} dot(%p0, %p1), lhs_contracting_dims={1}, rhs_contracting_dims={0}
}

%fused_computation.2 (p0: f32[2,3]) -> f32[2,3] {
  %p0 = f32[2,3]{1,0} parameter(0)
  ROOT %neg.2 = f32[2,3]{1,0} negate(%p0), metadata={op_name="jit(update)/jvp(Net.encode)/neg"}
}

ENTRY %main (a: f32[2,3], b: f32[3,4]) -> f32[2,4] {
  %a = f32[2,3]{1,0} parameter(0)
  %b = f32[3,4]{1,0} parameter(1)
  %fusion.2 = f32[2,3]{1,0} fusion(%a), kind=kLoop, calls=%fused_computation.2
  %add.3 = f32[2,3]{1,0} add(%fusion.2, %fusion.2), metadata={op_name="jit(update)/transpose(jvp(Net.core))/add"}
  %copy.4 = f32[3,4]{0,1} copy(%b)
  ROOT %fusion.1 = f32[2,4]{1,0} fusion(%add.3, %copy.4), kind=kCustom, calls=%fused_computation.1
}
"""
    ops = benchmark_profile.hlo_ops(text)
    assert ops["add.3"] == ("transpose(jvp(Net.core))/add", "f32[2,3]")
    assert ops["fusion.2"] == ("jvp(Net.encode)/neg", "f32[2,3]")  # from inside the fused computation
    assert ops["fusion.1"] == ("dot (no source recorded)", "f32[2,4]")
    assert ops["copy.4"] == ("copy (no source recorded)", "f32[3,4]")  # an instruction XLA added


def test_flop_count_multiplies_loops_and_matches_xla_without_them():
    a = jnp.ones((64, 64))
    ten = lambda a: jax.lax.scan(lambda c, _: (c @ a, None), a, None, length=10)[0]  # noqa: E731
    assert matmul_flops(ten, a) == (10 * 2 * 64**3, False)
    x, k = jnp.ones((2, 16, 16, 3)), jnp.ones((3, 3, 3, 8))
    conv = lambda x, k: jax.lax.conv_general_dilated(x, k, (1, 1), "VALID",  # noqa: E731
                                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    cost = jax.jit(conv).lower(x, k).cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    assert matmul_flops(conv, x, k) == (2 * 2 * 14 * 14 * 8 * 3 * 9, False) and cost["flops"] == 2 * 2 * 14 * 14 * 8 * 3 * 9
    loop = lambda a: jax.lax.while_loop(lambda c: c[1] < 3, lambda c: (c[0] @ a, c[1] + 1), (a, 0))[0]  # noqa: E731
    assert matmul_flops(loop, a) == (2 * 64**3, True)  # counted once, flagged


def test_profile_command_names_every_configuration():
    assert {"quickstart", "image_goals_cpu", "house_rooms_cpu", "paper"} <= set(benchmark.CONFIG_NAMES)


def test_train_benchmark_in_several_processes(monkeypatch, capsys, tmp_path):
    """Each process runs `benchmark train` on one configuration with --json; the table
    sums their frames/s. The pool is replaced by one that runs the first command in this
    process (on the tiny learner) and gives the others its result with another
    frames/s; `run_pool` itself is tested in test_workers.py."""
    pools = []

    def pool(commands, jobs, logs):
        pools.append((len(commands), jobs))
        for command in commands:
            assert command[:4] == [sys.executable, "-m", "a2catvn_jax.benchmark", "train"]
        benchmark.main(commands[0][3:])
        first = commands[0][commands[0].index("--json") + 1]
        for i, command in enumerate(commands[1:], 1):
            (row,) = json.loads(open(first).read())
            open(command[command.index("--json") + 1], "w").write(json.dumps([{**row, "train_fps": 100.0 * i}]))
        return [0] * len(commands)

    monkeypatch.setattr(workers, "run_pool", pool)
    monkeypatch.setattr(workers, "available_cores", lambda: [0, 1, 2])  # whatever this host's affinity allows
    tiny = TINY_LEARNER + ["env.scene.num_scenes=1"] + ONLY_DEPTH
    out = tmp_path / "rows.json"
    benchmark.main(["train", "--configs", "quickstart", "--updates", "1", "--processes", "2", "--json", str(out),
                    "--set", *tiny])
    assert pools == [(2, 2)]
    (two,) = json.loads(out.read_text())
    assert two["processes"] == 2 and two["cores"] == [2, 1] and len(two["train_fps"]) == 2
    assert two["train_fps"][0] > 0 and two["train_fps"][1] == 100.0
    assert two["train_fps_total"] == sum(two["train_fps"])
    printed = capsys.readouterr().out
    assert f"{two['train_fps_total']:15.0f}" in printed and "train fps, all" in printed


def test_train_benchmark_at_several_batch_sizes(monkeypatch, capsys, tmp_path):
    """--batch-sizes: one process per size, one at a time, each with env.num_envs set;
    the rows carry each size's memory. The pool runs each command in this process on
    the tiny learner (its peak resident memory is this process's)."""
    pools = []

    def pool(commands, jobs, logs):
        pools.append((len(commands), jobs))
        for command in commands:
            benchmark.main(command[3:])
        return [0] * len(commands)

    monkeypatch.setattr(workers, "run_pool", pool)
    _one_second_per_reading(monkeypatch)  # the rates are exactly the work of one interval
    tiny = TINY_LEARNER + ["env.scene.num_scenes=1"] + ONLY_DEPTH
    out = tmp_path / "rows.json"
    benchmark.main(["train", "--configs", "quickstart", "--updates", "1", "--batch-sizes", "4", "6", "--json", str(out),
                    "--set", *tiny])
    assert pools == [(1, 1), (1, 1)]
    rows = json.loads(out.read_text())
    assert [r["batch"] for r in rows] == [4, 6]  # 4: the tiny learner's, compiled by the test above (cache)
    for r in rows:
        assert (r["init_s"], r["compile_s"], r["first_s"]) == (1.0, 1.0, 1.0)
        assert r["train_fps"] == 4 * r["batch"]  # one update of 4-step rollouts in the timed second
        assert r["env_fps"] == 2 * 4 * r["batch"]  # two rollouts of 4 steps, random actions
        assert 0 < r["state_gib"] < r["peak_rss_gib"] and 0 < r["update_gib"] < 1
    # The replay keeps every environment of these small batches: the state grows with B.
    assert rows[1]["state_gib"] > rows[0]["state_gib"]
    assert "peak GiB" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(["train", "--processes", "1", "--batch-sizes", "16"])
    assert exit_info.value.code == 2 and "not both" in capsys.readouterr().err


def test_train_benchmark_process_failure_is_one_line(monkeypatch, capsys, tmp_path):
    def pool(commands, jobs, logs):
        for log in logs:
            log.write_text("Traceback ...\nRuntimeError: out of memory\n")
        return [1] * len(commands)

    monkeypatch.setattr(workers, "run_pool", pool)
    with pytest.raises(SystemExit) as exit_info:
        benchmark.main(["train", "--configs", "quickstart", "--processes", "1"])
    assert exit_info.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: a benchmark process failed (exit status 1): RuntimeError: out of memory"]

    def killed(commands, jobs, logs):
        return [-9] * len(commands)

    monkeypatch.setattr(workers, "run_pool", killed)
    with pytest.raises(SystemExit):
        benchmark.main(["train", "--configs", "paper", "--batch-sizes", "4096"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "killed by signal 9 (the kernel's out-of-memory killer" in err[0] and "4096" in err[0]


def _one_second_per_reading(monkeypatch):
    """The benchmarks' clock moves one second per reading: each timed pass takes 1 s."""
    clock = itertools.count()
    monkeypatch.setattr(throughput, "time", types.SimpleNamespace(perf_counter=lambda: float(next(clock))))


def test_network_benchmark_compares_conv_impls(capsys, tmp_path, monkeypatch):
    """`benchmark network --conv-impls`: every listed implementation timed, one row per network."""
    _one_second_per_reading(monkeypatch)
    out = tmp_path / "rows.json"
    benchmark.main(["network", "--resolution", "16", "--frames", "4", "--targets", "2", "--repeats", "2",
                    "--conv-impls", "xla", "matmul", "--json", str(out), "--set", *TINY_LEARNER])
    (row,) = json.loads(out.read_text())
    assert row["network"] == "default" and set(row["fps"]) == {"xla", "matmul"}
    assert row["fps"] == {"xla": 4.0, "matmul": 4.0}  # 4 frames per (1 s) pass
    assert "conv_impl=matmul" in capsys.readouterr().out


def test_network_benchmark_times_each_pass_and_the_stream_layers(capsys, tmp_path, monkeypatch):
    """`benchmark network`: JAX as trained, JAX per frame and (when installed) PyTorch;
    `--layers`: conv1 and conv2 of the image stream each way, with auto's choice."""
    _one_second_per_reading(monkeypatch)
    out = tmp_path / "rows.json"
    small = ["--resolution", "16", "--frames", "4", "--targets", "2", "--repeats", "2", "--json", str(out),
             "--set", *TINY_LEARNER]
    benchmark.main(["network", *small])
    (row,) = json.loads(out.read_text())
    assert row["jax_fps"] == row["jax_per_frame_fps"] == 4.0  # 4 frames per (1 s) pass
    assert row["torch_fps"] in (None, 4.0)
    benchmark.main(["network", "--layers", *small])
    (row,) = json.loads(out.read_text())
    layers = row["layers"]
    assert set(layers) == {"conv1", "conv2"}
    assert layers["conv1"]["shape"] == "8x8/4, 3 -> 4 channels, 16x16 input"
    assert layers["conv2"]["shape"] == "4x4/2, 4 -> 8 channels, 4x4 input"
    for r in layers.values():
        assert r["xla"] == r["matmul"] == 1000.0 and r["auto"] in ("xla", "matmul") and r.get("torch", 1000.0) == 1000.0
    assert "conv2 (4x4/2, 4 -> 8 channels, 4x4 input): XLA convolution" in capsys.readouterr().out


def test_compile_benchmark_times_the_compile_alone_at_each_batch(monkeypatch, capsys, tmp_path):
    """`benchmark compile`: the update compiled on the abstract state at each batch (nothing
    run); the program is the same size at both batches, and XLA's buffers grow with B."""
    _one_second_per_reading(monkeypatch)
    out = tmp_path / "rows.json"
    benchmark.main(["compile", "--configs", "quickstart", "--batch-sizes", "4", "16", "--json", str(out),
                    "--set", *TINY_LEARNER, "env.scene.num_scenes=1", *ONLY_DEPTH])
    small, large = json.loads(out.read_text())
    assert (small["batch"], large["batch"]) == (4, 16)
    for r in (small, large):
        assert (r["build_s"], r["trace_s"], r["compile_s"]) == (1.0, 1.0, 1.0)
    assert small["hlo_ops"] > 1000 and abs(large["hlo_ops"] - small["hlo_ops"]) < 0.1 * small["hlo_ops"]
    assert large["update_gib"] > 2 * small["update_gib"] > 0
    printed = capsys.readouterr().out
    assert "HLO ops" in printed and f"{large['hlo_ops']:8d}" in printed


def test_loop_benchmark_times_the_update_with_the_houses_as_an_argument(capsys, tmp_path):
    """`benchmark loop --houses-argument` times the update compiled with the houses as an
    argument (as `train.new_houses_every` runs it) beside the one with them compiled in;
    `--per-call` with no value leaves the device loop out."""
    out = tmp_path / "loop.json"
    benchmark.main(["loop", "--configs", "quickstart", "--updates", "1", "--repeats", "1", "--per-call",
                    "--houses-argument", "--json", str(out), "--set", *TINY_LEARNER, "env.scene.num_scenes=2",
                    *ONLY_DEPTH])
    (row,) = json.loads(out.read_text())
    assert set(row["fps"]) == {"1 update, host read", "1 update, houses as argument"}
    assert all(fps > 0 for fps in row["fps"].values())
    assert "houses as argument" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--per-call", "0", "5"], "loop: --per-call 0: must be >= 1"),
    (["--per-call", "--houses-argument", "--set", "env.render.backend=mjx"],
     "train.new_houses_every: new houses are rendered by the ray caster"),
])
def test_loop_benchmark_refuses_in_one_line(args, message, capsys):
    """What no run does is refused before anything compiles: a device loop of fewer than
    one update per call, the houses as an argument where a run cannot renew them."""
    with pytest.raises(SystemExit):
        benchmark.main(["loop", "--configs", "quickstart", *args])
    err = capsys.readouterr().err
    assert message in err.strip().splitlines()[-1] and "Traceback" not in err


def test_loop_benchmark_refuses_houses_argument_where_auto_resolves_to_mjx(capsys, monkeypatch):
    """`env.render.backend=auto` resolves to mjx on an accelerator, which the
    configuration cannot see: the built world's renderer is checked, as training does."""
    from a2catvn_jax.env import NavEnv
    monkeypatch.setattr(NavEnv, "renderer", property(lambda self: "mjx"))
    with pytest.raises(SystemExit):
        benchmark.main(["loop", "--configs", "quickstart", "--updates", "1", "--repeats", "1", "--per-call",
                        "--houses-argument", "--set", *TINY_LEARNER, "env.scene.num_scenes=2", *ONLY_DEPTH])
    err = capsys.readouterr().err
    assert "this run renders with 'mjx'" in err.strip().splitlines()[-1] and "Traceback" not in err
