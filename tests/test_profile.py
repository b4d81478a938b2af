"""`benchmark profile`: every phase of the update is timed and the parts add up to about
the whole (A2C with one auxiliary term, on the tiny learner, to keep compiles few)."""

from __future__ import annotations

from a2catvn_jax import benchmark
from a2catvn_jax.bench.profile import AUX_TERMS, profile_update
from a2catvn_jax.config import load_config
from tiny import TINY_LEARNER

ONLY_DEPTH = [f"train.loss_weights.{t}=0" for t in AUX_TERMS if t != "depth"]


def test_profile_times_every_phase_of_the_update():
    cfg = load_config(None, TINY_LEARNER + ["env.scene.kind=room", "env.scene.num_scenes=1"] + ONLY_DEPTH)
    r = profile_update(cfg, repeats=2)
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
    assert r["update_flops"] > 0 and r["update_gflops_per_s"] > 0


def test_profile_command_names_every_configuration():
    assert {"quickstart", "image_goals_cpu", "house_rooms_cpu", "paper"} <= set(benchmark.CONFIG_NAMES)
