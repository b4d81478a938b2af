"""`env.render.backend`: what `auto` chooses and why, and the `mjx` backend's errors.

Pixel-for-pixel agreement with `mujoco.mj_ray` is in test_render.py (path "mjx"), and
the environment's tests run with each backend in test_env.py."""

from __future__ import annotations

import types

import jax
import pytest

from a2catvn_jax.config import load_config
from a2catvn_jax.env import NavEnv, backends, mjx_render
from a2catvn_jax.errors import UserError

BASE = ["env.num_envs=4", "env.render.image_size=16", "env.render.culling=false", "env.scene.kind=room",
        "env.scene.num_scenes=1", "env.goals_per_scene=2"]


@pytest.mark.parametrize("faster", ["raycast", "mjx"])
def test_auto_measures_both_backends_and_takes_the_faster(monkeypatch, faster):
    """Each backend renders the batch of 4 three times after a warm-up; a clock that makes
    one render 1 s and the other's 0.5 s gives rates of exactly 4 and 8 frames/s."""
    monkeypatch.setattr(backends, "RATES", backends.Memo("test"))
    seconds = {"raycast": 0.5 if faster == "raycast" else 1.0, "mjx": 0.5 if faster == "mjx" else 1.0}
    readings = []
    for backend in backends.BACKENDS:  # two readings per timed render, three renders each
        readings += [x for k in range(3) for x in (0.0, seconds[backend])]
    clock = iter(readings)
    monkeypatch.setattr(backends, "time", types.SimpleNamespace(perf_counter=lambda: next(clock)))
    env = NavEnv(load_config(None, BASE + ["env.render.backend=auto"]).env)
    (rates,) = backends.RATES.values()
    assert rates == {b: 4 / seconds[b] for b in ("raycast", "mjx")}
    assert env.world.backend == faster
    assert env.world.backend_note.startswith(f"env.render.backend auto: {faster} (")
    assert f"raycast {4 / seconds['raycast']:.0f} frames/s, mjx {4 / seconds['mjx']:.0f} frames/s" in env.world.backend_note
    # A second world of the same camera, batch and layout reuses the measurement.
    monkeypatch.setattr(backends, "measure", lambda *a, **k: pytest.fail("measured twice"))
    again = NavEnv(load_config(None, BASE + ["env.render.backend=auto"]).env)
    assert again.world.backend == env.world.backend


@pytest.mark.parametrize("backend", ["auto", "mjx"])
def test_without_warp(monkeypatch, backend):
    """Without the warp-lang package, `auto` renders with raycast and says why; `mjx`
    is a one-line error that names the package."""
    monkeypatch.setattr(mjx_render, "unavailable", lambda: "it needs the warp-lang package (pip install warp-lang)")
    cfg = load_config(None, BASE + [f"env.render.backend={backend}"]).env
    if backend == "auto":
        env = NavEnv(cfg)
        assert env.world.backend == "raycast" and "warp-lang" in env.world.backend_note
    else:
        with pytest.raises(UserError, match=r"^env.render.backend 'mjx': it needs the warp-lang package") as e:
            NavEnv(cfg)
        assert "\n" not in str(e.value)


def test_unknown_backend_is_a_config_error():
    with pytest.raises(UserError, match="env.render.backend"):
        load_config(None, ["env.render.backend=opengl"])


def test_env_benchmark_times_both_backends(tmp_path, capsys, monkeypatch):
    """`benchmark env` runs each backend on the same episodes, one row each: 2 steps of
    2 environments per timed interval."""
    import itertools
    import json

    from a2catvn_jax import benchmark
    from a2catvn_jax.bench import throughput

    wall, cpu = itertools.count(), itertools.count()
    monkeypatch.setattr(throughput, "time", types.SimpleNamespace(perf_counter=lambda: float(next(wall)),
                                                                  process_time=lambda: float(next(cpu))))

    out = tmp_path / "env.json"
    benchmark.main(["env", "--batch-sizes", "2", "--resolutions", "16", "--steps", "2", "--no-gl", "--json", str(out),
                    "--set", "env.scene.kind=room", "env.render.culling=false", "env.goals_per_scene=1"])
    rows = json.loads(out.read_text())
    assert [r["backend"] for r in rows] == ["raycast", "mjx"]
    for r in rows:  # each clock reads one second later than the last: every interval is 1 s
        assert r["batch"] == 2 and r["resolution"] == 16
        assert r["frames_per_s"] == 2 * 2 and r["cores"] == 1.0 and r["compile_s"] == 1.0
    assert "backend" in capsys.readouterr().out


def test_mjx_worlds_must_share_one_layout():
    """A world of another geom layout passed to an environment rendered by `mjx` (its
    render context fixes the layout) is a one-line error, not a wrong image; worlds
    built with one layout render."""
    from a2catvn_jax.env import world as world_lib
    from a2catvn_jax.env.scenes.mjcf import layout_of

    cfg = load_config(None, BASE + ["env.render.backend=mjx"]).env
    own, others = world_lib.make_scenes(cfg), world_lib.make_scenes(cfg, 7)
    layout = layout_of(own + others)
    env = NavEnv(cfg, world=world_lib.World(cfg, own, layout=layout))
    other = world_lib.World(cfg, others, layout={**layout, "box": layout["box"] + 3})
    with pytest.raises(UserError, match="one geom layout") as e:
        env.reset(jax.random.PRNGKey(0), world=other.arrays)
    assert "\n" not in str(e.value)
    same = world_lib.World(cfg, others, layout=layout)
    state = jax.jit(lambda k, w: env.reset(k, world=w))(jax.random.PRNGKey(0), same.arrays)
    assert float(state.obs.depth.max()) > 0


def test_render_benchmark_draws_the_same_frames_with_each_renderer(tmp_path, capsys):
    """`benchmark render` times the ray caster, `mjx.render` and MuJoCo Warp called
    directly, each in a process pinned to one core, on the same house and poses: the
    geom ids of every renderer agree with the ray caster's (a wrong pose or scene in any
    of them would show here)."""
    import json

    from a2catvn_jax import benchmark

    out = tmp_path / "render.json"
    benchmark.main(["render", "--batch-sizes", "2", "--resolutions", "16", "--repeats", "1", "--json", str(out)])
    rows = json.loads(out.read_text())
    assert [r["renderer"] for r in rows] == ["raycast", "mjx", "warp"]
    for r in rows:
        assert r["batch"] == 2 and r["resolution"] == 16 and r["frames_per_s"] > 0
        assert r["pinned_cores"] == 1 and 0 < r["cores"] < 1.2
    assert rows[0]["same_geom_as_raycast"] is None
    assert all(r["same_geom_as_raycast"] >= 0.99 for r in rows[1:])
    assert "per core" in capsys.readouterr().out
