"""The experiment runner: run naming and sharing, statistics, the report, and a tiny
end-to-end experiment that trains, evaluates, plots, writes its section and resumes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from a2catvn_jax.run import experiments as ex
from tiny import TINY_LEARNER

TINY = TINY_LEARNER + ["env.max_episode_steps=10", "train.total_frames=32", "train.log_every=1",
                       "train.checkpoint_every=1"]


def quiet(*_):
    pass


def test_every_experiment_has_both_configs_and_plans():
    for exp in ex.EXPERIMENTS.values():
        for scale in ex.SCALES:
            runs = ex.plan(exp, scale, [0, 1], "/tmp/unused")
            assert len(runs) == 2 * len(exp.variants)
            assert {r.cfg.seed for r in runs} == {0, 1}
            # Variants differ in their configuration (or pre-training), so in their work directory.
            assert len({r.workdir.parent for r in runs}) == len(exp.variants)


def test_shared_variants_share_runs_and_seeds_do_not():
    aux, curriculum = ex.EXPERIMENTS["aux"], ex.EXPERIMENTS["curriculum"]
    a = ex.plan(aux, "cpu", [0], "/r")[0]
    c = ex.plan(curriculum, "cpu", [0], "/r")
    assert c[0].workdir == a.workdir  # "no curriculum" is A2CAT-VN as configured
    assert c[1].workdir != a.workdir and c[1].cfg.train.curriculum
    pre = ex.plan(ex.EXPERIMENTS["pretraining"], "cpu", [0], "/r")
    assert pre[1].workdir != a.workdir and pre[1].cfg == a.cfg  # same config, pre-trained: another run
    s0, s1 = ex.plan(aux, "cpu", [0, 1], "/r")[:2]
    assert s0.workdir.parent == s1.workdir.parent and s0.workdir != s1.workdir


def test_unknown_scale_and_bad_overrides_are_errors():
    with pytest.raises(ex.ExperimentError, match="scale"):
        ex.EXPERIMENTS["aux"].config_path("laptop")
    with pytest.raises(ValueError, match="train.no_such_key"):
        ex.plan(ex.EXPERIMENTS["aux"], "cpu", [0], "/r", ["train.no_such_key=1"])


def test_statistics():
    values = np.array([[1.0, 2.0], [2.0, 4.0], [4.0, 9.0]])
    mean, half = ex.t_interval(values)
    low, high = stats.t.interval(0.95, 2, loc=values.mean(0), scale=stats.sem(values, axis=0))
    np.testing.assert_allclose(mean, values.mean(0))
    np.testing.assert_allclose(mean - half, low)
    np.testing.assert_allclose(mean + half, high)
    np.testing.assert_allclose(ex.t_interval(values[:1])[1], 0.0)
    np.testing.assert_allclose(ex.standard_error(values), stats.sem(values, axis=0))
    np.testing.assert_allclose(ex.standard_error(values[:2]), np.abs(values[0] - values[1]) / 2)  # the range
    np.testing.assert_allclose(ex.smooth(np.array([1.0, np.nan, 3.0, 5.0]), 2), [1.0, 1.0, 3.0, 4.0])
    curve = {"frames": np.array([10.0, 20.0, 30.0]), "success_rate": np.array([0.2, 0.75, 0.6])}
    assert ex.frames_to_threshold(curve, 0.7) == 20.0
    assert ex.frames_to_threshold(curve, 0.8) is None


def test_section_replaces_its_own_block_only(tmp_path):
    md = tmp_path / "results.md"
    md.write_text("# Results\n\nhand-written text\n")
    exp = ex.EXPERIMENTS["aux"]
    ex.write_section(md, exp, "cpu", "first")
    ex.write_section(md, ex.EXPERIMENTS["memory"], "cpu", "other")
    ex.write_section(md, exp, "cpu", "second")
    text = md.read_text()
    assert "hand-written text" in text and "other" in text and "second" in text and "first" not in text
    assert text.count("<!-- experiment aux cpu -->") == 1


@pytest.fixture(scope="module")
def tiny_experiment(tmp_path_factory):
    root = tmp_path_factory.mktemp("experiments")
    exp = ex.Experiment(
        "tiny", "tiny comparison", "image_goals",
        (ex.Variant("full"), ex.Variant("no depth", ("train.loss_weights.depth=0",)), ex.Variant("full again")),
        threshold=0.9, cpu_threshold=0.5, evaluations=("train",),
    )
    # "no depth" was stopped before its first checkpoint: an empty checkpoint directory
    stopped = next(run for run in ex.plan(exp, "cpu", [3], root / "runs", TINY) if run.variant.label == "no depth")
    (stopped.workdir / "checkpoints").mkdir(parents=True)
    lines = []
    summary = ex.run_experiment(exp, scale="cpu", seeds=[3], episodes=2, root=root / "runs", docs=root / "docs",
                                overrides=TINY, command="tiny", compilation_cache=False, log=lines.append)
    return exp, root, summary, lines


def test_tiny_experiment_reports(tiny_experiment):
    exp, root, summary, lines = tiny_experiment
    # "full again" reuses "full"; "no depth", stopped before any checkpoint, starts from scratch
    assert sorted(line.split(",")[0] for line in lines if line.startswith(("training ", "resuming "))) == [
        "training full", "training no depth"]
    assert set(summary["variants"]) == {"full", "no depth", "full again"}
    full, again = summary["variants"]["full"], summary["variants"]["full again"]
    assert full["workdirs"] == again["workdirs"] and full["seeds"] == [3]
    assert full["frames"] == [16.0, 32.0]  # one log row per update of 4 envs x 4 steps
    assert len(full["success_rate"]["mean"]) == 2 and full["success_rate"]["sem"] == [0.0, 0.0]
    assert summary["threshold"] == 0.5 and summary["random"]["train"]["success_rate"] >= 0.0
    for v in summary["variants"].values():
        result = v["eval"]["train"]
        assert len(result["success_rate"]) == 1 and 0.0 <= result["spl"][0] <= result["success_rate"][0] <= 1.0
    saved = json.loads((root / "runs" / "cpu" / "tiny.json").read_text())
    assert saved["variants"]["no depth"]["eval"] == summary["variants"]["no depth"]["eval"]
    assert (root / "docs" / "experiments" / "tiny_cpu.png").stat().st_size > 0
    text = (root / "docs" / "results.md").read_text()
    assert "<!-- experiment tiny cpu -->" in text and "| no depth |" in text and "uniformly random policy" in text


def test_tiny_experiment_resumes_without_training(tiny_experiment):
    exp, root, summary, _ = tiny_experiment
    lines = []
    again = ex.run_experiment(exp, scale="cpu", seeds=[3], episodes=2, root=root / "runs", docs=root / "docs",
                              overrides=TINY, command="tiny", compilation_cache=False, log=lines.append)
    assert not any(line.startswith(("training ", "resuming ")) for line in lines)
    assert again["variants"]["no depth"]["eval"] == summary["variants"]["no depth"]["eval"]
