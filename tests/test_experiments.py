"""The experiment runner: run naming and sharing, statistics, the report, and a tiny
end-to-end experiment that trains, evaluates, stores, plots and writes its section;
then, with the work directories deleted, re-tabulates from the store alone, refuses an
evaluation that needs a checkpoint, and trains only an added seed."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

from a2catvn_jax import experiments as cli
from a2catvn_jax.config import CONFIGS, Config, load_config, to_dict
from a2catvn_jax.errors import Interrupted
from a2catvn_jax.run.plots import smooth
from a2catvn_jax.study import compare, formats, registry, report, runner, stats
from a2catvn_jax.study import store as st
from a2catvn_jax.study.registry import EXPERIMENTS, SCALES, ExperimentError, Variant
from tiny import TINY_LEARNER

# Plain A2C (no auxiliary loss, no replay): the smallest training program to compile.
TINY = TINY_LEARNER + list(registry.NO_VN + registry.NO_UNREAL) + [
    "env.max_episode_steps=10", "train.total_frames=32", "train.log_every=1", "train.checkpoint_every=1"]


def test_every_experiment_has_both_configs_and_plans():
    for exp in EXPERIMENTS.values():
        for scale in registry.SCALES:
            runs = st.plan(exp, scale, [0, 1], "/tmp/unused", store="/tmp/store")
            assert len(runs) == 2 * len(exp.variants)
            assert {r.cfg.seed for r in runs} == {0, 1}
            # Variants differ in their configuration (or pre-training), so in their work directory.
            assert len({r.workdir.parent for r in runs}) == len(exp.variants)
            assert all(r.stored.relative_to("/tmp/store") == r.workdir.relative_to("/tmp/unused") for r in runs)


def test_every_experiment_has_the_blind_control_of_its_task():
    # The configured agent on images of zeros, in every experiment: the same run (so the
    # same work directory) wherever two experiments share a task (configuration and setting).
    blind_dirs = {}
    for exp in EXPERIMENTS.values():
        for scale in registry.SCALES:
            controls = [r for r in st.plan(exp, scale, [0], "/r") if r.cfg.agent.blind == "both"]
            assert [r.variant for r in controls] == [registry.BLIND_CONTROL], exp.name
            path = exp.config_path(scale)
            curves = st.curve_overrides(exp, controls[0].cfg, 0)  # what the run evaluates while it trains
            assert controls[0].cfg == load_config(path, [*exp.setting, "seed=0", "agent.blind=true", *curves])
            assert blind_dirs.setdefault((scale, path, exp.setting), controls[0].workdir) == controls[0].workdir


def test_the_authors_variants_are_the_preset_and_the_documented_settings():
    # The network variant is configs/presets/authors_network.yaml (padded for 32 px), the
    # loss variant the `--set` line of docs/method.md, so the experiment follows both.
    quickstart = CONFIGS / "quickstart.yaml"
    preset = CONFIGS / "presets" / "authors_network.yaml"
    assert load_config(quickstart, registry.AUTHORS_NETWORK) == load_config([quickstart, preset],
                                                                            ["agent.conv_padding=same"])
    method = (Path(__file__).parents[1] / "docs" / "method.md").read_text()
    documented = method.split("The authors' loss settings in one line")[1].split("```")[1]
    assert documented.replace("--set", " ").replace("\\", " ").split() == list(registry.AUTHORS_LOSSES)
    labels = [v.label for v in EXPERIMENTS["authors"].variants]
    assert labels[0] == "A2CAT-VN" and EXPERIMENTS["authors"].variants[0] == EXPERIMENTS["sight"].variants[0]
    assert len(labels) == 4


def test_the_large_batch_preset_is_the_batch_experiments_recipe():
    """configs/presets/large_batch.yaml holds what the batch experiment's "B 64, 5-step
    rollouts, clip 40" trains, so the preset is the configuration the evidence is for."""
    base = CONFIGS / "image_goals_cpu.yaml"
    (recipe,) = [v for v in EXPERIMENTS["batch"].variants if v.label == "B 64, 5-step rollouts, clip 40"]
    assert load_config(base, recipe.overrides) == load_config([base, CONFIGS / "presets" / "large_batch.yaml"])


def test_learning_by_sight_experiments():
    aux, ablations, gen = (EXPERIMENTS[n] for n in ("aux", "ablations", "generalisation"))
    assert [v.label for v in aux.variants] == ["A2CAT-VN (pre-trained)", "A2CAT-VN", "A2C+UNREAL", "A2C",
                                               "blind A2CAT-VN"]
    for exp in (aux, gen):
        blind = [r for r in st.plan(exp, "cpu", [0], "/r") if r.variant.label == "blind A2CAT-VN"]
        assert len(blind) == 1 and blind[0].cfg.agent.blind == "both"
    runs = st.plan(ablations, "cpu", [0], "/r")
    assert runs[0].workdir == st.plan(aux, "cpu", [0], "/r")[1].workdir  # the full A2CAT-VN is shared
    weights = registry.AUX_LOSSES
    for run, loss in zip(runs[1:-2], weights, strict=True):
        w = run.cfg.train.loss_weights
        assert getattr(w, loss) == 0 and all(getattr(w, other) > 0 for other in weights if other != loss)
    # Then all three visual-navigation losses at once and the blind control: the aux experiment's runs.
    assert [r.workdir for r in runs[-2:]] == [r.workdir for r in st.plan(aux, "cpu", [0], "/r")[2::2]]
    assert aux.threshold_at("cpu") == ablations.threshold_at("cpu") == gen.threshold_at("cpu") == 0.5
    sight = EXPERIMENTS["sight"]
    assert sight.config_path("cpu") == sight.config_path("paper") == CONFIGS / "quickstart.yaml"
    seeing, blind = st.plan(sight, "cpu", [0], "/r")
    assert seeing.cfg.agent.blind == "none" and blind.cfg.agent.blind == "both"
    assert seeing.cfg == load_config(CONFIGS / "quickstart.yaml", ["seed=0"])
    aux_qs = EXPERIMENTS["aux_quickstart"]
    runs = {r.variant.label: r for r in st.plan(aux_qs, "cpu", [0], "/r")}
    assert runs["A2CAT-VN"].workdir == seeing.workdir  # shares the sight experiment's runs
    assert runs["A2CAT-VN (pre-trained)"].variant.pretrain and runs["A2CAT-VN (pre-trained)"].cfg.pretrain.epochs == 10
    assert runs["A2C"].cfg.train.loss_weights.reward_prediction == 0 and runs["A2C+UNREAL"].cfg.train.loss_weights.depth == 0
    assert runs["A2C+UNREAL"].cfg.train.loss_weights.pixel_control > 0
    abl_qs = st.plan(EXPERIMENTS["ablations_quickstart"], "cpu", [0], "/r")
    assert abl_qs[0].workdir == seeing.workdir and len(abl_qs) == 3 + len(weights)  # the full A2CAT-VN is sight's
    for run, loss in zip(abl_qs[1:-2], weights, strict=True):
        w = run.cfg.train.loss_weights
        assert getattr(w, loss) == 0 and all(getattr(w, other) > 0 for other in weights if other != loss)
        assert run.cfg.env == seeing.cfg.env
    assert [r.workdir for r in abl_qs[-2:]] == [runs["A2C+UNREAL"].workdir, blind.workdir]  # stored already
    # the stored seeds and the listing look for its runs under the same single configuration
    assert st.stored_seeds(sight, "cpu", "/nonexistent") == {"A2CAT-VN": [], "blind A2CAT-VN": []}
    assert "(configs/quickstart.yaml;" in report.listing("/nonexistent", names=["sight"])


def test_shared_variants_share_runs_and_seeds_do_not(tmp_path):
    """Run keys alone (an empty store)."""
    store = tmp_path / "store"
    aux, curriculum = EXPERIMENTS["aux"], EXPERIMENTS["curriculum"]
    pre, a = st.plan(aux, "cpu", [0], "/r", store=store)[:2]
    c = st.plan(curriculum, "cpu", [0], "/r", store=store)
    assert c[1].workdir == a.workdir  # the CPU task is configured with its curriculum
    assert c[0].workdir != a.workdir and not c[0].cfg.train.curriculum
    paper = st.plan(curriculum, "paper", [0], "/r", store=store)
    assert paper[0].workdir == st.plan(aux, "paper", [0], "/r", store=store)[1].workdir  # the paper-sized one without
    assert pre.workdir != a.workdir and pre.cfg == a.cfg  # same config, pre-trained: another run
    assert st.plan(EXPERIMENTS["pretraining"], "cpu", [0], "/r", store=store)[1].workdir == pre.workdir
    s0, s1 = st.plan(aux, "cpu", [0, 1], "/r", store=store)[:2]
    assert s0.workdir.parent == s1.workdir.parent and s0.workdir != s1.workdir


def test_the_clip_40_comparison_shares_runs_and_keeps_every_loss(tmp_path):
    store = tmp_path / "store"
    runs = {r.variant.label: r for r in st.plan(EXPERIMENTS["aux_clip40"], "cpu", [0], "/r", store=store)}
    clipping = {r.variant.label: r for r in st.plan(EXPERIMENTS["clipping"], "cpu", [0], "/r", store=store)}
    aux = {r.variant.label: r for r in st.plan(EXPERIMENTS["aux"], "cpu", [0], "/r", store=store)}
    assert runs["A2CAT-VN, clip 40"].workdir == clipping["A2CAT-VN, clip 40"].workdir
    assert runs["A2C"].workdir == aux["A2C"].workdir and runs["blind A2CAT-VN"].workdir == aux["blind A2CAT-VN"].workdir
    pre, unreal = runs["A2CAT-VN (pre-trained), clip 40"], runs["A2C+UNREAL, clip 40"]
    assert pre.variant.pretrain and pre.cfg == runs["A2CAT-VN, clip 40"].cfg
    assert pre.workdir not in (runs["A2CAT-VN, clip 40"].workdir, aux["A2CAT-VN (pre-trained)"].workdir)
    assert pre.cfg.train.max_grad_norm == unreal.cfg.train.max_grad_norm == 40
    assert unreal.cfg.train.loss_weights == aux["A2C+UNREAL"].cfg.train.loss_weights
    w = pre.cfg.train.loss_weights
    assert all(getattr(w, loss) > 0 for loss in registry.AUX_LOSSES)
    assert aux["A2CAT-VN"].cfg.train.max_grad_norm == 0.5


def test_unknown_scale_and_bad_overrides_are_errors():
    with pytest.raises(ExperimentError, match="scale"):
        EXPERIMENTS["aux"].config_path("laptop")
    with pytest.raises(ValueError, match="train.no_such_key"):
        st.plan(EXPERIMENTS["aux"], "cpu", [0], "/r", ["train.no_such_key=1"])


def test_statistics():
    values = np.array([[1.0, 2.0], [2.0, 4.0], [4.0, 9.0]])
    mean, half = stats.t_interval(values)
    low, high = scipy.stats.t.interval(0.95, 2, loc=values.mean(0), scale=scipy.stats.sem(values, axis=0))
    np.testing.assert_allclose(mean, values.mean(0))
    np.testing.assert_allclose(mean - half, low)
    np.testing.assert_allclose(mean + half, high)
    np.testing.assert_allclose(stats.t_interval(values[:1])[1], 0.0)
    np.testing.assert_allclose(stats.standard_error(values), scipy.stats.sem(values, axis=0))
    np.testing.assert_allclose(smooth(np.array([1.0, np.nan, 3.0, 5.0]), 2), [1.0, 1.0, 3.0, 4.0])
    curve = {"frames": np.array([10.0, 20.0, 30.0]), "success_rate": np.array([0.2, 0.75, 0.6])}
    assert stats.frames_to_threshold(curve, 0.7) == 20.0
    assert stats.frames_to_threshold(curve, 0.8) is None
    # Only where the running mean is over a full window: 1.0 at the first row, alone, does not count.
    rows = [{"frames": 10.0 * (i + 1), "success_rate": x} for i, x in enumerate([1.0] + [0.1] * 36 + [0.9] * 3)]
    early = stats.curves(rows)  # 40 rows: a window of 4
    assert early["window"] == 4 and early["success_rate"][0] == 1.0 and early["success_rate"][1] == 0.55
    assert stats.frames_to_threshold(early, 0.5) == 390.0  # (0.1 + 0.1 + 0.9 + 0.9) / 4 at row 38
    # 20 rows: the last 10% is rows 18-19, the 10% before it rows 16-17; None and NaN rows left out
    rows = [{"success_rate": 0.1}] * 16 + [{"success_rate": 0.4}, {"success_rate": 0.6},
                                           {"success_rate": 0.7}, {"success_rate": None}]
    assert stats.final_success(rows) == pytest.approx(0.7)
    assert stats.late_change(rows) == pytest.approx(0.7 - 0.5)
    # 16 rows: the last 2 vs the 2 before
    assert stats.late_change(rows[:12] + rows[-4:][::-1]) == pytest.approx(0.5 - 0.7)
    assert math.isnan(stats.late_change(rows[:1]))
    assert formats.format_estimate([0.05, -0.01, 0.03], -1.0, 1.0, "{:+.2f}".format) == "+0.02 [-0.05, +0.10]"


def test_t_interval_by_hand():
    # 0.5 .. 0.9: mean 0.7, sample sd sqrt(0.1 / 4), standard error sd / sqrt(5) = 0.0707107;
    # t quantile 0.975 with 4 degrees of freedom (tables): 2.776445.
    est = stats.estimate([0.5, 0.6, 0.7, 0.8, 0.9])
    half = 2.776445 * math.sqrt(0.1 / 4) / math.sqrt(5)
    assert est.n == 5 and est.mean == pytest.approx(0.7)
    assert est.low == pytest.approx(0.7 - half, abs=1e-6) and est.high == pytest.approx(0.7 + half, abs=1e-6)
    assert formats.format_estimate([0.5, 0.6, 0.7, 0.8, 0.9]) == "0.70 [0.50, 0.90]"
    # clipped to the possible range; one value: no interval; missing values are counted
    assert formats.format_estimate([0.9, 1.0]) == "0.95 [0.31, 1.00]"
    assert formats.format_estimate([0.25]) == "0.25"
    assert formats.format_estimate([0.5, None, 0.7, math.nan]) == "0.60 [0.00, 1.00] (n=2)"
    assert formats.format_estimate([None, None]) == "–"


def test_frames_to_threshold_formatting():
    # reached: 400k, 500k; t(0.975, 1) = 12.706 x standard error 50k: [-185k, 1085k], clipped at 0
    assert formats.format_frames([400e3, None, 500e3], 2e6) == "450k [0, 1.1M], 2/3 reached; 1 not by 2.0M"
    assert formats.format_frames([300e3, 300e3], 4e5) == "300k [300k, 300k], 2/2 reached"
    assert formats.format_frames([300e3], 4e5) == "300k, 1/1 reached"
    assert formats.format_frames([None, None, None], 4e5) == "0/3 reached by 400k"
    p = stats.welch_p([100.0, 110.0, 120.0], [400.0, 400.0, 390.0])
    assert p == pytest.approx(scipy.stats.ttest_ind([100, 110, 120], [400, 400, 390], equal_var=False).pvalue)
    assert stats.welch_p([1.0], [2.0, 3.0]) is None and stats.welch_p([4.0, 4.0], [4.0, 4.0]) is None


def test_section_replaces_its_own_block_only(tmp_path):
    md = tmp_path / "results.md"
    md.write_text("# Results\n\nhand-written text\n")
    exp = EXPERIMENTS["aux"]
    report.write_section(md, exp, "cpu", "first")
    report.write_section(md, EXPERIMENTS["memory"], "cpu", "other")
    report.write_section(md, exp, "cpu", "second")
    text = md.read_text()
    assert "hand-written text" in text and "other" in text and "second" in text and "first" not in text
    assert text.count("<!-- experiment aux cpu -->") == 1


def test_trimmed_log_keeps_the_resumed_rows_and_few_bytes(tmp_path):
    row = {"update": 0, "frames": 0, "fps": 1234.5678, "loss/actor": 0.0123456789, "success_rate": 0.30645161290322,
           "episode_length": 92.48387096774194, "spl": math.nan, "episodes": 62}
    rows = [{**row, "update": u, "frames": 320 * u} for u in (20, 40, 60, 40, 60, 80)]  # resumed at 40
    trimmed = st.trim_log(rows)
    assert [r["update"] for r in trimmed] == [20, 40, 60, 80]
    assert set(trimmed[0]) <= set(st.STORED_COLUMNS) and "fps" not in trimmed[0]
    assert trimmed[0]["success_rate"] == 0.3065 and math.isnan(trimmed[0]["spl"])


# "b" differs from "a" only in bookkeeping, so it has its own runs but shares the compiled programs.
TINY_VARIANTS = (Variant("a"), Variant("b", ("train.keep_checkpoints=2",)), Variant("a again"))


def tiny(variants=TINY_VARIANTS, name="tiny"):
    return registry.Experiment(name, "tiny comparison", "image_goals", variants, threshold=0.9, cpu_threshold=0.5,
                         evaluations=("train",))


def run_tiny(root, exp=None, seeds=(0, 1), episodes=2, **kw):
    lines = []
    opts = runner.Options(scale="cpu", seeds=seeds, episodes=episodes, root=root / "runs", docs=root / "docs",
                          store=root / "store", overrides=TINY, command="tiny", compilation_cache=False, **kw)
    summary = runner.run_experiment(exp or tiny(), opts, log=lines.append)
    return summary, lines


def same(a, b) -> bool:
    """Equal, NaN included (a tiny run's log rows have no finished episode)."""
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def trained_runs(lines):
    return sorted(line.split(" in ")[0] for line in lines if line.startswith(("training ", "resuming ")))


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("experiments")
    # "b", seed 0, was stopped before its first checkpoint: an empty checkpoint directory
    stopped = next(r for r in st.plan(tiny(), "cpu", [0], root / "runs", TINY, root / "store")
                   if r.variant.label == "b")
    (stopped.workdir / "checkpoints").mkdir(parents=True)
    summary, lines = run_tiny(root)
    return root, summary, lines, (root / "docs" / "results.md").read_text()


@pytest.fixture(scope="module")
def from_store(trained):
    """The same experiment again after the work directories (checkpoints, logs) are deleted."""
    root = trained[0]
    shutil.rmtree(root / "runs")
    summary, lines = run_tiny(root)
    return summary, lines, (root / "docs" / "results.md").read_text()


def test_tiny_experiment_trains_stores_and_reports(trained):
    root, summary, lines, text = trained
    # "a again" reuses "a"; "b", stopped before any checkpoint, starts from scratch
    assert trained_runs(lines) == ["training a, seed 0", "training a, seed 1", "training b, seed 0",
                                   "training b, seed 1"]
    assert set(summary["variants"]) == {"a", "b", "a again"}
    a, again = summary["variants"]["a"], summary["variants"]["a again"]
    assert a["runs"] == again["runs"] and a["seeds"] == [0, 1]
    assert a["frames"] == [16.0, 32.0]  # one log row per update of 4 envs x 4 steps
    assert len(a["success_rate"]["mean"]) == 2 and len(a["frames_to_threshold"]) == 2
    assert summary["threshold"] == 0.5
    assert a["welch_p_eval_success_vs_first"] is None
    assert set(summary["variants"]["b"]["welch_p_eval_success_vs_first"]) == {"train"}
    for policy in ("random", "oracle"):
        assert 0.0 <= summary["baselines"][policy]["train"]["success_rate"] <= 1.0
    for v in summary["variants"].values():
        result = v["eval"]["train"]
        assert len(result["success_rate"]) == 2
        assert all(0.0 <= spl <= s <= 1.0 for spl, s in zip(result["spl"], result["success_rate"]))
    store = root / "store"
    for rel in a["runs"] + summary["variants"]["b"]["runs"]:
        d = store / rel
        seed = int(rel.rsplit("_", 1)[1])  # every policy is evaluated with the seed 1000 + the run's seed
        evals = {f"eval_train_{policy}_2_seed{1000 + seed}.json": policy for policy in ("sample", "greedy")}
        assert {p.name for p in d.iterdir()} == {"config.yaml", "variant.json", "metrics.jsonl", "experiment_time.json",
                                                 "done.json", *evals}
        for name, policy in evals.items():
            result = json.loads((d / name).read_text())
            assert (result["policy"], result["seed"], result["episodes"]) == (policy, 1000 + seed, 2)
        done = json.loads((d / "done.json").read_text())
        assert done["updates"] == 2 and done["frames"] == 32 and done["machine"] and done["date"]
        assert set(json.loads((d / "metrics.jsonl").read_text().splitlines()[0])) <= set(st.STORED_COLUMNS)
    baselines = {p.name.rsplit("_", 1)[0] for p in (store / "cpu" / "image_goals" / "baselines").iterdir()}
    assert baselines == {"random_train_2_seed999", "oracle_train_2_seed999"}
    assert summary["baselines"]["random"]["train"]["seed"] == 999
    for key in ("eval", "eval_greedy"):
        e = a[key]["train"]
        assert e["eval_seed"] == [1000, 1001] and e["episodes"] == [2, 2]
        assert e["pooled"]["episodes"] == 4 and e["pooled"]["successes"] == sum(e["successes"])
    assert json.loads((store / "cpu" / "tiny.json").read_text())["variants"]["b"]["eval"] == summary["variants"]["b"]["eval"]
    from matplotlib.image import imread

    figure = imread(root / "docs" / "experiments" / "tiny_cpu.png")  # two panels of curves, bands and lines
    assert figure.shape[1] > figure.shape[0] > 100 and len(np.unique(figure.reshape(-1, figure.shape[-1]), axis=0)) > 20
    assert "<!-- experiment tiny cpu -->" in text and "| b |" in text
    assert "| uniformly random policy | – | – |" in text and "| shortest-path oracle | – | – |" in text
    assert "95% t-interval" in text and "Seeds: 0, 1 (2 runs per variant)" in text
    assert "| a | greedy | " in text and "| a | sampled | " in text and "Wilson's 95% score interval" in text
    assert ("Evaluation at complexity 1: sampled policy: 2 episodes per run and house set, seed 1000 + the run's seed; "
            "greedy policy: 2 episodes per run and house set, seed 1000 + the run's seed; baselines: 2 episodes, "
            "seed 999.") in text


def test_listing_counts_stored_seeds(trained, monkeypatch, capsys):
    root = trained[0]
    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny())
    cli.main(["--list", "tiny", "--scale", "cpu", "--docs", str(root / "docs"), "--store", str(root / "store"),
              "--set", *TINY])
    out = capsys.readouterr().out
    assert "cpu   a: 2 stored (seeds 0, 1)" in out and "cpu   b: 2 stored (seeds 0, 1)" in out


def test_store_alone_reproduces_the_results(trained, from_store):
    root, summary, _, text = trained
    again, lines, text_again = from_store
    assert not any((root / "runs").rglob("checkpoints"))
    assert trained_runs(lines) == [] and not any(line.startswith("evaluating") for line in lines)
    for key in ("frames", "success_rate", "episode_length", "frames_to_threshold", "final_success", "late_change",
                "eval"):
        for label in summary["variants"]:
            assert same(again["variants"][label][key], summary["variants"][label][key]), (label, key)
    assert same(again["baselines"], summary["baselines"])
    assert text_again == text


def test_missing_evaluation_needs_the_checkpoint(trained, from_store, monkeypatch, capsys):
    root = trained[0]
    with pytest.raises(ExperimentError, match=r"a, seed 0 .*3 episodes, seed 1000 .*eval_train_sample_2_seed1000.json"
                                              r".*final checkpoint"):
        run_tiny(root, episodes=3)
    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny())
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny", "--seeds", "0", "1", "--episodes", "3", "--docs", str(root / "docs"), "--store",
                  str(root / "store"), "--root", str(root / "runs"), "--set", *TINY])
    assert exit_info.value.code == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith("error: a, seed 0 (")
    # --skip-missing: the stored evaluations of 2 episodes, said to be so, not the 3 asked for
    summary, lines = run_tiny(root, episodes=3, skip_missing=True)
    stored = from_store[0]["variants"]["a"]
    for key in ("eval", "eval_greedy"):
        assert summary["variants"]["a"][key]["train"]["success_rate"] == stored[key]["train"]["success_rate"]
        assert summary["variants"]["a"][key]["train"]["episodes"] == [2, 2]
    assert "no checkpoint for the 3 episodes with seed 1000 asked for: a, seed 0: train sample, train greedy: " \
           "stored 2 episodes, seed 1000" in lines
    section = (root / "docs" / "results.md").read_text()
    assert ("sampled policy: 2 episodes per run and house set, seed 1000 + the run's seed (stored evaluations, "
            "reported instead of the 3 episodes, seed 1000 + the run's seed asked for") in section
    assert summary["variants"]["a"]["final_success"] == from_store[0]["variants"]["a"]["final_success"]


def test_an_added_seed_trains_only_that_seed(trained, from_store):
    root = trained[0]
    one = tiny((Variant("a"),), name="tiny_a")
    summary, lines = run_tiny(root, one, seeds=(0, 1, 2))
    assert trained_runs(lines) == ["training a, seed 2"]
    assert summary["variants"]["a"]["seeds"] == [0, 1, 2] and len(summary["variants"]["a"]["eval"]["train"]["spl"]) == 3
    assert "3 runs per variant" in (root / "docs" / "results.md").read_text()
    assert st.stored_seeds(one, "cpu", root / "store", TINY) == {"a": [0, 1, 2]}


def test_all_stored_reports_each_variants_stored_runs_part_way(trained, from_store, monkeypatch, capsys):
    root = trained[0]
    run_tiny(root, tiny((Variant("a"),), name="tiny_a"), seeds=(0, 1, 2))  # "a" has seed 2 stored, "b" not
    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny())
    where = ["--episodes", "2", "--docs", str(root / "docs"), "--store", str(root / "store"), "--root",
             str(root / "nowhere"), "--set", *TINY]
    cli.main(["tiny", "--all-stored", *where])
    assert not trained_runs(capsys.readouterr().out.splitlines())
    summary = json.loads((root / "store" / "cpu" / "tiny.json").read_text())
    assert [summary["variants"][v]["seeds"] for v in ("a", "b", "a again")] == [[0, 1, 2], [0, 1], [0, 1, 2]]
    assert len(summary["variants"]["a"]["eval"]["train"]["success_rate"]) == 3
    text = (root / "docs" / "results.md").read_text()
    assert "Seeds: a 0–2 (3); b 0, 1 (2); a again 0–2 (3)." in text
    cli.main(["tiny", "--stored-seeds", *where])  # the seeds stored for every variant
    assert "Seeds: 0, 1 (2 runs per variant)." in (root / "docs" / "results.md").read_text()
    # A variant with no stored run is left out of the part-way report and named in it ...
    c = Variant("c", ("train.max_grad_norm=1",))
    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny(TINY_VARIANTS + (c,)))
    capsys.readouterr()
    cli.main(["tiny", "--all-stored", *where])
    assert "left out of this part-way report, none of their runs stored yet: 'c'" in capsys.readouterr().out
    summary = json.loads((root / "store" / "cpu" / "tiny.json").read_text())
    assert list(summary["variants"]) == ["a", "b", "a again"] and summary["not_stored"] == ["c"]
    text = (root / "docs" / "results.md").read_text()
    assert "Not in this part-way report, no run stored yet: c." in text and "| c |" not in text
    # ... but not the first variant, the one the others are compared with: one line that names it.
    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny((c,) + TINY_VARIANTS))
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny", "--all-stored", *where])
    assert exit_info.value.code == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith("error: tiny: no run of 'c' (the variant the others are compared")


def test_jobs_train_each_run_by_the_runners_own_command(trained, from_store, monkeypatch, capsys):
    """`--jobs N`: each run to train is one process running the runner's own command for
    that (seed, variant) with --no-report, N at a time; the parent reports from the
    store. The pool is replaced here by one that runs each command in this process."""
    root = trained[0]
    one = tiny((Variant("a"), Variant("a again")), name="tiny_jobs")  # one run per seed, two variants
    monkeypatch.setitem(EXPERIMENTS, one.name, one)
    where = ["--docs", str(root / "docs"), "--store", str(root / "store"), "--root", str(root / "runs"), "--set", *TINY]
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny_jobs", "--seeds", "7", "--jobs", "999", *where])
    assert exit_info.value.code == 2
    assert "999 processes need at least 999 CPU cores" in capsys.readouterr().err

    pools = []

    def pool(commands, jobs, logs, on_start, on_end):
        pools.append((commands, jobs, logs))
        for i, command in enumerate(commands):
            assert command[:3] == [sys.executable, "-m", "a2catvn_jax.experiments"] and "--no-report" in command
            on_start(i, [0])
            cli.main(command[3:])
            on_end(i, 0)
        return [0] * len(commands)

    monkeypatch.setattr(runner, "run_pool", pool)
    summary, lines = run_tiny(root, one, seeds=(0, 1, 5), jobs=2)
    (commands, jobs, logs), = pools
    assert jobs == 2 and len(commands) == 1 and logs[0].name == "train.log" and logs[0].parent.name == "seed_5"
    assert "started a, seed 5 on core(s) 0; log: " + str(logs[0]) in lines
    assert any(line.startswith("stored: a, seed 5 (") for line in lines)
    assert summary["variants"]["a"]["seeds"] == summary["variants"]["a again"]["seeds"] == [0, 1, 5]
    assert "training a, seed 5" in capsys.readouterr().out  # the process's own output
    # a process that fails is named with its log, and nothing is reported
    monkeypatch.setattr(runner, "run_pool", lambda commands, jobs, logs, on_start, on_end: [1] * len(commands))
    with pytest.raises(ExperimentError, match=r"1 of 1 run\(s\) failed: a, seed 6 \(log: .*seed_6/train.log\)"):
        run_tiny(root, one, seeds=(0, 6), jobs=2)


def test_an_interrupted_run_stops_the_runner_and_the_same_command_resumes_it(tmp_path, monkeypatch):
    """A run whose training stops early with a checkpoint (what Ctrl-C or SIGTERM does to
    the training loop; here it returns after one of its two updates) is neither evaluated
    nor stored: the runner stops with an error naming it, and the same command resumes it
    from that checkpoint to its end."""
    exp = tiny((Variant("a"),), name="tiny_interrupted")
    real = runner.train
    monkeypatch.setattr(runner, "train", lambda *args, **kw: real(*args, **kw, max_updates=1))
    with pytest.raises(Interrupted, match=r"interrupted: a, seed 0 stopped at update 1 of 2 with a "
                                         r"checkpoint in .*seed_0; the same command resumes it"):
        run_tiny(tmp_path, exp, seeds=(0,))
    (run,) = st.plan(exp, "cpu", [0], tmp_path / "runs", TINY, tmp_path / "store")
    assert not run.is_stored()
    monkeypatch.setattr(runner, "train", real)
    summary, lines = run_tiny(tmp_path, exp, seeds=(0,), report=False)
    assert trained_runs(lines) == ["resuming a, seed 0"] and run.is_stored()
    assert summary == {"experiment": "tiny_interrupted", "trained": ["a, seed 0"]}


def test_a_second_ctrl_c_aborts_the_runner_with_one_line(tmp_path, monkeypatch, capsys):
    """A second Ctrl-C while a run trains in the runner's own process (`--jobs 1`) ends the
    command with one line and exit status 130, not a traceback."""
    exp = tiny((Variant("a"),), name="tiny_aborted")
    monkeypatch.setitem(EXPERIMENTS, exp.name, exp)

    def aborted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "train", aborted)
    with pytest.raises(SystemExit) as exit_info:
        cli.main([exp.name, "--seeds", "0", "--docs", str(tmp_path / "docs"), "--store", str(tmp_path / "store"),
                  "--root", str(tmp_path / "runs"), "--set", *TINY])
    assert exit_info.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["aborted: the run in training keeps only its last checkpoint; the same command resumes each "
                   "unfinished run from its last checkpoint"]


def test_the_run_key_hashes_the_differences_from_the_defaults():
    """A key added to the schema with its default renames no run; a value that differs
    from its default, pre-training and the environment do (the seed does not)."""
    quickstart = CONFIGS / "quickstart.yaml"
    cfg = load_config(quickstart, ["seed=3"])
    values, defaults = to_dict(cfg), to_dict(Config())
    key = st.run_key(cfg, False)
    assert key == st.config_key(values, defaults) == st.run_key(load_config(quickstart, ["seed=4"]), False)
    # the canonical form: sorted JSON of the dotted differences, seed left out, then "|pretrain"
    assert st.config_key({"seed": 1, "a": {"b": 2, "c": [1]}, "d": 0}, {"seed": 0, "a": {"b": 1, "c": [1]}, "d": 0},
                         True) == hashlib.sha256(b'{"a.b": 2}|pretrain').hexdigest()[:8]
    # a new key at its default, in a section or as a section of its own: the same key
    grown, grown_defaults = copy.deepcopy(values), copy.deepcopy(defaults)
    for d in (grown, grown_defaults):
        d["train"]["new_key"] = 7
        d["new_section"] = {"size": [1, 2]}
    assert st.config_key(grown, grown_defaults) == key
    # the new key set to another value, another value of an existing key, pre-training: another key
    grown["train"]["new_key"] = 8
    assert st.config_key(grown, grown_defaults) != key
    assert st.run_key(load_config(quickstart, ["train.max_grad_norm=40"]), False) != key
    assert st.run_key(cfg, True) != key
    # a key set explicitly to its default is no difference
    default_clip = Config().train.max_grad_norm
    assert cfg.train.max_grad_norm == default_clip
    assert st.run_key(load_config(quickstart, [f"train.max_grad_norm={default_clip}"]), False) == key
    # the baselines' key: the environment section alone
    assert st.env_key(load_config(quickstart, ["train.max_grad_norm=40"])) == st.env_key(cfg)
    assert st.env_key(load_config(quickstart, ["env.max_episode_steps=7"])) != st.env_key(cfg)


def test_a_run_is_found_under_its_own_key_only(trained, from_store, tmp_path):
    """The planner looks at STORE/SCALE/CONFIG/RUN_KEY/seed_N alone: a run moved to
    another key is not found (it is trained again), one under its key is."""
    store = tmp_path / "store"
    shutil.copytree(trained[0] / "store", store)
    exp = tiny((Variant("a"),))
    s0, s1 = st.plan(exp, "cpu", [0, 1], tmp_path / "runs", TINY, store)
    assert s0.is_stored() and s1.is_stored() and s0.relative.split("/")[2] == st.run_key(s0.cfg, False)
    other_key = s1.stored.parent.with_name("0000aaaa")
    other_key.mkdir()
    s1.stored.rename(other_key / "seed_1")
    s0, s1 = st.plan(exp, "cpu", [0, 1], tmp_path / "runs", TINY, store)
    assert s0.is_stored() and not s1.is_stored()
    seeds = st.stored_seeds(exp, "cpu", store, TINY)["a"]
    assert 0 in seeds and 1 not in seeds


def test_train_only_some_variants(trained, from_store, monkeypatch):
    """`train_only` trains the named variants' missing runs and reports nothing while
    other variants' runs are missing; an unknown label is an error naming the variants."""
    root = trained[0]
    with pytest.raises(ExperimentError, match=r"tiny has no variant 'c'; its variants: 'a', 'b', 'a again'"):
        run_tiny(root, train_only=["c"])
    monkeypatch.setattr(runner, "train_run", lambda run, log: pytest.fail(f"trained {run.name}"))
    summary, lines = run_tiny(root, seeds=(0, 1, 3), train_only=[])
    assert summary["experiment"] == "tiny" and set(summary) == {"experiment", "pending"}
    assert sorted(summary["pending"]) == ["a again, seed 3", "a, seed 3", "b, seed 3"]
    assert lines[-1].startswith("not reported: 3 run(s)")
    summary, _ = run_tiny(root, seeds=(0, 1), train_only=["b"])  # all stored: reported as before
    assert summary["variants"]["b"]["seeds"] == [0, 1]


def test_a_stored_report_compares_with_another_experiments(trained, from_store):
    """`--compare` reads what `run_experiment` stored: the same numbers as the report's own
    tests for two variants of one experiment, and the runs' logged gradient norms."""
    root, summary, _, _ = trained
    store = root / "store"
    text = compare.compare(["tiny:a", "tiny:b"], "cpu", store)
    a, = [line for line in text.splitlines() if line.startswith("| a | tiny | 0, 1 |")]
    norms = [json.loads(line)["grad_norm"] for rel in summary["variants"]["a"]["runs"]
             for line in (store / rel / "metrics.jsonl").read_text().splitlines()]
    assert a.endswith(f"| {sum(g > 0.5 for g in norms)}/{len(norms)} (clip 0.5) |")  # the default clip
    v = summary["variants"]["a"]
    frames = formats.format_frames(v["frames_to_threshold"], v["frames_max"])
    final = formats.format_estimate(v["final_success"])
    assert f"| {frames} | {final} |" in a
    assert "each log row holds one update's" in text  # TINY logs every update
    b, = [line for line in text.splitlines() if line.startswith("| b (tiny) |")]
    p = summary["variants"]["b"]["welch_p_frames_vs_first"]
    assert b.split("|")[2].strip() == ("–" if p is None else f"{p:.2g}")


def test_plan_prints_one_self_contained_command_per_unfinished_run(tmp_path, capsys):
    """`--plan`: a command per run neither stored nor shared with another variant; a stored
    run drops out. Each command trains that one run (`--train-only` its label, its seed)."""
    import shlex

    store, root = tmp_path / "store", tmp_path / "root"
    args = ["sight", "--plan", "--seeds", "7", "--store", str(store), "--root", str(root)]
    cli.main(args)
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    commands = [shlex.split(line) for line in lines]
    assert [c[c.index("--train-only") + 1] for c in commands] == ["A2CAT-VN", "blind A2CAT-VN"]
    assert all(c[:3] == ["python", "-m", "a2catvn_jax.experiments"] and c[c.index("--seeds") + 1] == "7"
               and c[c.index("--store") + 1] == str(store) for c in commands)
    seeing = st.plan(EXPERIMENTS["sight"], "cpu", [7], root, store=store)[0]
    seeing.stored.mkdir(parents=True)
    (seeing.stored / st.DONE).write_text("{}\n")
    cli.main(args)
    assert [shlex.split(line)[shlex.split(line).index("--train-only") + 1]
            for line in capsys.readouterr().out.strip().splitlines()] == ["blind A2CAT-VN"]


def test_the_navigation_experiments_levers_and_the_presets_controls():
    nav = EXPERIMENTS["navigation"]
    assert [v.label for v in nav.variants] == [
        "A2CAT-VN", "A2CAT-VN, clip 40", "A2CAT-VN without reward prediction", "A2CAT-VN, clip 40, 256 houses",
        "A2CAT-VN, clip 40, new houses every 200k frames", "A2CAT-VN, clip 40, 256 houses, 20M frames",
        "blind A2CAT-VN"]
    runs = {r.variant.label: r for r in st.plan(nav, "cpu", [0], "/r")}
    renewed = runs["A2CAT-VN, clip 40, new houses every 200k frames"].cfg
    assert renewed.train.new_houses_every * renewed.train.rollout_length * renewed.env.num_envs == 200_000
    assert runs["blind A2CAT-VN"].cfg.agent.blind == "both"
    longer = runs["A2CAT-VN, clip 40, 256 houses, 20M frames"].cfg
    assert longer.train.total_frames == 4 * runs["A2CAT-VN, clip 40, 256 houses"].cfg.train.total_frames
    assert longer.train.eval.every == 4 * runs["A2CAT-VN, clip 40, 256 houses"].cfg.train.eval.every
    generalisation = {r.variant.label: r.workdir for r in st.plan(EXPERIMENTS["generalisation"], "cpu", [0], "/r")}
    assert runs["A2CAT-VN"].workdir == generalisation["A2CAT-VN"]  # the stored runs are kept
    assert runs["blind A2CAT-VN"].workdir == generalisation["blind A2CAT-VN"]
    # ... though only the navigation runs evaluate held-out houses while they train: five
    # times per run (5M frames of 320 per update), with the run's evaluation seed.
    for seed in (0, 3):
        ec = st.plan(nav, "cpu", [seed], "/r")[0].cfg.train.eval
        assert (ec.every, ec.episodes, ec.houses, ec.policies, ec.seed) == (
            15625 // 5, st.CURVE_EPISODES, ("held-out",), ("sample",), 1000 + seed)
    assert st.plan(EXPERIMENTS["generalisation"], "cpu", [0], "/r")[0].cfg.train.eval.every == 0

    # The preset's experiment: the preset, the paper's settings, and the three controls
    # (the blind one and A2CAT-VN shared with the generalisation experiment, the preset's
    # run with the navigation experiment's lever of the same settings).
    preset = {r.variant.label: r for r in st.plan(EXPERIMENTS["navigation_preset"], "cpu", [0], "/r")}
    assert list(preset) == ["navigation preset", "A2CAT-VN", "blind A2CAT-VN", "target-blind navigation preset",
                            "observation-blind navigation preset"]
    assert preset["navigation preset"].workdir == runs["A2CAT-VN, clip 40, 256 houses"].workdir
    assert preset["A2CAT-VN"].workdir == generalisation["A2CAT-VN"]
    assert preset["blind A2CAT-VN"].workdir == generalisation["blind A2CAT-VN"]
    for mode in ("target", "observation"):
        control = preset[f"{mode}-blind navigation preset"].cfg
        assert control.agent.blind == mode
        assert dataclasses.replace(control, agent=dataclasses.replace(control.agent, blind="none")) \
            == preset["navigation preset"].cfg


def test_an_experiments_setting_is_every_variants_and_every_baselines_task():
    """`Experiment.setting` overrides the configuration of every run and of the baselines:
    declared_success trains the preset and its target-blind and blind controls with the
    stop action, under run keys of their own."""
    exp = EXPERIMENTS["declared_success"]
    runs = {r.variant.label: r for r in st.plan(exp, "cpu", [0], "/r")}
    preset = {r.variant.label: r for r in st.plan(EXPERIMENTS["navigation_preset"], "cpu", [0], "/r")}
    for label, run in runs.items():
        assert run.cfg.env.stop_action
        assert run.workdir != preset[label].workdir
        without = dataclasses.replace(run.cfg, env=dataclasses.replace(run.cfg.env, stop_action=False))
        assert without == preset[label].cfg
    assert runs["target-blind navigation preset"].cfg.agent.blind == "target"
    assert st.task_config(exp, "cpu").env.stop_action  # the baselines' environment
    assert not st.task_config(EXPERIMENTS["navigation_preset"], "cpu").env.stop_action
    plain = registry.Experiment("plain", "hand-made", "house_rooms", exp.variants)
    assert st.plan(plain, "cpu", [0], "/r")[0].workdir == preset["navigation preset"].workdir


def test_the_navigation_preset_is_the_preset_experiments_variant():
    """configs/presets/navigation.yaml holds what the navigation_preset experiment's
    "navigation preset" trains, so the preset is the configuration the evidence is for."""
    for scale in SCALES:
        base = EXPERIMENTS["navigation_preset"].config_path(scale)
        (preset,) = [v for v in EXPERIMENTS["navigation_preset"].variants if v.label == "navigation preset"]
        assert load_config(base, preset.overrides) == load_config([base, CONFIGS / "presets" / "navigation.yaml"])


def test_held_out_curves_are_stored_summarised_and_drawn(tmp_path):
    """A run's evaluations during training (eval.jsonl) are stored with it and read back;
    `summarise` averages them over the runs at the frames all of them evaluated at; the
    report's figure gets a third panel and its section says what it shows."""
    a, b = Variant("a"), Variant("b", ("train.max_grad_norm=40",))
    exp = registry.Experiment("curves", "hand-made", "image_goals", (a, b), evaluations=("held-out",),
                              held_out_points=2)
    run = st.plan(exp, "cpu", [0], tmp_path / "runs", TINY, tmp_path / "store")[0]
    assert run.cfg.train.eval.every == 1  # 2 updates, 2 points
    run.workdir.mkdir(parents=True)
    (run.workdir / "metrics.jsonl").write_text(json.dumps({"update": 2, "frames": 32, "success_rate": 0.5}) + "\n")
    key = stats.HELD_OUT_CURVE
    rows = [{"update": u, "frames": 16 * u, key: 0.123456789 * u} for u in (1, 2)]
    (run.workdir / "eval.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    st.store_run(run, {})
    assert st.run_record(run, {}).eval_log == tuple({**r, key: round(r[key], 4)} for r in rows)

    def log(rates):
        return [{"frames": 1e5 * (i + 1), "success_rate": r} for i, r in enumerate(rates)]

    def curve(points):
        return tuple({"update": int(f // 320), "frames": f, key: v} for f, v in points)

    done = {"date": "2026-01-01T00:00:00+00:00", "machine": "m", "git": None}
    records = [
        stats.RunRecord(a, 0, "a0", log([0.1] * 10), {}, 60.0, done, curve([(5e5, 0.2), (1e6, 0.4)])),
        stats.RunRecord(a, 1, "a1", log([0.1] * 10), {}, 60.0, done, curve([(5e5, 0.3), (1e6, 0.6), (1.5e6, 0.7)])),
        stats.RunRecord(b, 0, "b0", log([0.1] * 10), {}, 60.0, done),
    ]
    summary = stats.summarise(exp, records, {"random": {"held-out": {**_result([False] * 9 + [True], 999), "episode_length": 9.5}}}, 0.5)
    va, vb = summary["variants"]["a"], summary["variants"]["b"]
    assert va["held_out_curve"]["frames"] == [5e5, 1e6] and va["held_out_curve"]["runs"] == 2
    assert va["held_out_curve"]["mean"] == pytest.approx([0.25, 0.5])
    assert va["held_out_curve"]["half_width_95"] == pytest.approx(list(stats.t_interval([[0.2, 0.4], [0.3, 0.6]])[1]))
    assert vb["held_out_curve"] is None
    summary.update(scale="cpu", episodes=4, eval_seed_offset=1000, baseline_eval_seed=999, max_episode_steps=10,
                   not_stored=[])
    text = report.section(exp, "cpu", summary, "cmd", "img.png")
    assert "Third panel: success in held-out houses during training" in text and "(a 2) with its 95% t-band" in text
    from matplotlib.image import imread

    report.plot(summary, tmp_path / "three.png", "with curves")
    for v in summary["variants"].values():
        v["held_out_curve"] = None
    report.plot(summary, tmp_path / "two.png", "without")
    assert imread(tmp_path / "three.png").shape[1] > imread(tmp_path / "two.png").shape[1]
    assert "Third panel" not in report.section(exp, "cpu", summary, "cmd", "img.png")


def _result(successes, seed, episodes=None, spl=0.1):
    episodes = len(successes) if episodes is None else episodes
    return {"success_rate": sum(successes) / episodes, "spl": spl, "episodes": episodes, "seed": seed,
            "per_episode": {"success": list(successes)}}


def test_summary_censors_frames_to_threshold_and_pools_episodes():
    """`summarise` on hand-made records: frames to threshold of the runs that never reach
    it censored at their own last frame (restricted mean up to the shortest run's, log-rank
    against the first variant), both policies' evaluations pooled over episodes; and the
    section's tables and tests from it."""
    a, b = Variant("a"), Variant("b", ("train.max_grad_norm=40",))
    exp = registry.Experiment("syn", "hand-made", "image_goals", (a, b), evaluations=("train", "held-out"))

    def log(rates):  # 10 rows or more: no smoothing (a running mean over 1 row)
        return [{"frames": 1e5 * (i + 1), "success_rate": r} for i, r in enumerate(rates)]

    def evals(seed, greedy_seed=None, greedy_episodes=None):
        return {"sample": {"train": _result([True, False, True, True], 1000 + seed),
                           "held-out": _result([False, False, True, False], 1000 + seed)},
                "greedy": {"train": _result([True] * 3 + [False] * (greedy_episodes or 1),
                                            1000 + seed if greedy_seed is None else greedy_seed),
                           "held-out": None}}

    done = {"date": "2026-01-01T00:00:00+00:00", "machine": "m", "git": None}
    records = [
        stats.RunRecord(a, 0, "a0", log([0.0, 0.2, 0.6] + [0.7] * 7), evals(0), 60.0, done),  # reaches at 300k
        stats.RunRecord(a, 1, "a1", log([0.1] * 10), evals(1), 60.0, done),  # censored at 1M
        stats.RunRecord(b, 0, "b0", log([0.0] * 6 + [0.5] * 4), evals(0), 60.0, done),  # reaches at 700k
        stats.RunRecord(b, 1, "b1", log([0.2] * 12), evals(1, greedy_seed=0, greedy_episodes=5), 60.0, done),
    ]
    base = {"random": {"train": _result([True] + [False] * 9, 999), "held-out": _result([False] * 10, 999)},
            "oracle": {"train": _result([True] * 10, 999), "held-out": _result([True] * 9 + [False], 999)}}
    summary = stats.summarise(exp, records, base, 0.5)
    va, vb = summary["variants"]["a"], summary["variants"]["b"]
    assert summary["rmst_horizon"] == 1e6 and vb["frames_last"] == [1e6, 1.2e6]
    assert va["frames_to_threshold"] == [3e5, None] and vb["frames_to_threshold"] == [7e5, None]
    assert va["rmst_frames"] == stats.restricted_mean([3e5, 1e6], [True, False], 1e6)
    # a: S = 1 up to 300k, then 1/2 to the horizon: 300k + 700k / 2
    assert va["rmst_frames"]["mean"] == pytest.approx(6.5e5)
    assert vb["rmst_frames"] == stats.restricted_mean([7e5, 1.2e6], [True, False], 1e6)
    assert vb["logrank_p_frames_vs_first"] == pytest.approx(
        stats.logrank_p([3e5, 1e6], [True, False], [7e5, 1.2e6], [True, False]))
    # Welch's test keeps counting a run that never reaches it at the variant's longest run
    assert vb["welch_p_frames_vs_first"] == pytest.approx(stats.welch_p([3e5, 1e6], [7e5, 1.2e6]))
    held = va["eval"]["held-out"]
    assert held["successes"] == [1, 1] and held["eval_seed"] == [1000, 1001]
    assert held["pooled"] == stats.pooled_success([1, 1], [4, 4])
    greedy = vb["eval_greedy"]
    assert greedy["train"]["episodes"] == [4, 8] and greedy["train"]["pooled"]["successes"] == 6
    assert greedy["held-out"]["success_rate"] == [None, None] and greedy["held-out"]["pooled"] is None
    assert vb["welch_p_eval_greedy_success_vs_first"]["train"] == pytest.approx(
        stats.welch_p([0.75, 0.75], [0.75, 3 / 8]))

    summary.update(scale="cpu", episodes=4, eval_seed_offset=1000, baseline_eval_seed=999, max_episode_steps=10,
                   not_stored=[])
    text = report.section(exp, "cpu", summary, "cmd", "img.png")
    row_a, = [line for line in text.splitlines() if line.startswith("| a | 300k, 1/2 reached; 1 not by 1.0M |")]
    assert f"| {formats.format_rmst(va['rmst_frames'])} |" in row_a
    greedy_b, = [line for line in text.splitlines() if line.startswith("| b | greedy |")]
    assert f"| {formats.format_pooled(greedy['train']['pooled'], 2)} |" in greedy_b and greedy_b.endswith("| – | – | – |")
    assert "| shortest-path oracle | – | – | 1.00 [0.72, 1.00] | 0.10 | – | 0.90 [0.60, 0.98] | 0.10 |" in text
    p = vb["logrank_p_frames_vs_first"]
    assert (f"Log-rank test on frames to threshold against a, a run that never reaches it censored at its last "
            f"frame: b p = {p:.2g}.") in text
    assert "Welch's t-test on evaluation success (training houses, greedy) against a: b p = " in text
    # b, seed 1's greedy evaluation used another seed and more episodes: the section says which
    assert ("greedy policy, evaluations that differ (asked for: 4 episodes, seed 1000 + the run's seed): a, training "
            "houses: seeds 0, 1 4 episodes, seed 1000 + the run's seed; b, training houses: seed 0 4 episodes, seed "
            "1000 + the run's seed, seed 1 8 episodes, seed 0; 4 of 8 evaluations (runs x house sets) not stored, "
            "left out") in text
    assert "sampled policy: 4 episodes per run and house set, seed 1000 + the run's seed; " in text
    assert "baselines: 10 episodes, seed 999 (stored, reported instead of the 4 episodes with seed 999 asked for)" in text
    # The tour (room-type goals only) has a row and a sentence where it has a result.
    assert "goal-blind tour" not in text
    summary["baselines"]["tour"] = {"train": _result([True] * 8 + [False] * 2, 999), "held-out": None}
    text = report.section(exp, "cpu", summary, "cmd", "img.png")
    assert any(line.startswith("| goal-blind tour of the rooms | – | – | – | – | 0.80 | ") for line in text.splitlines())
    assert "knows the map but not the goal" in text


def test_a_report_from_the_store_falls_back_on_older_evaluations_and_says_so(trained, from_store, tmp_path,
                                                                             monkeypatch, capsys):
    """Runs stored before the evaluation seed (their files named without it, seed 0 inside)
    and without greedy evaluations: the evaluation asked for is not taken from them; the
    command stops without --skip-missing or --no-evaluate, and with --no-evaluate reports
    them, evaluating nothing, saying what each number rests on."""
    store = tmp_path / "store"
    shutil.copytree(trained[0] / "store", store)
    runs = {(r.variant.label, r.seed): r for r in st.plan(tiny(), "cpu", [0, 1], tmp_path / "runs", TINY, store)}
    for seed in (0, 1):  # "a" (and "a again", the same runs) as stored before: seed 0, no greedy evaluation
        d = runs[("a", seed)].stored
        result = json.loads((d / f"eval_train_sample_2_seed{1000 + seed}.json").read_text())
        (d / f"eval_train_sample_2_seed{1000 + seed}.json").unlink()
        (d / f"eval_train_greedy_2_seed{1000 + seed}.json").unlink()
        (d / "eval_train_sample_2.json").write_text(json.dumps({**result, "seed": 0}))
    # a file named for the seed asked for that holds another seed's evaluation is not taken for it
    misnamed = runs[("b", 0)].stored / "eval_train_sample_2_seed1000.json"
    misnamed.write_text(json.dumps({**json.loads(misnamed.read_text()), "seed": 7}))
    assert st.saved_evaluations(runs[("b", 0)], ["train"], 2, "sample") == {}
    assert st.saved_evaluations(runs[("a", 0)], ["train"], 2, "sample") == {}
    assert st.saved_evaluations(runs[("a", 0)], ["train"], 2, "sample", seed=0)["train"]["seed"] == 0
    baselines = store / "cpu" / "image_goals" / "baselines"
    for other in baselines.glob("*.json"):  # those of other tests' episode counts
        if not other.name.startswith(("random_train_2_", "oracle_train_2_")):
            other.unlink()
    random_file, = baselines.glob("random_train_2_seed999_*.json")
    random_file.rename(baselines / random_file.name.replace("_seed999", ""))  # the random policy's, as stored before
    (baselines / random_file.name.replace("_seed999", "")).write_text(
        json.dumps({**json.loads((baselines / random_file.name.replace("_seed999", "")).read_text()), "seed": 0}))

    monkeypatch.setitem(EXPERIMENTS, "tiny", tiny())
    where = ["--episodes", "2", "--docs", str(tmp_path / "docs"), "--store", str(store), "--root",
             str(tmp_path / "runs"), "--set", *TINY]
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny", "--stored-seeds", *where])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a, seed 0 (" in err[0] and "2 episodes, seed 1000" in err[0] and "--no-evaluate" in err[0]
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny", "--stored-seeds", "--skip-missing", "--no-evaluate", *where])
    assert exit_info.value.code == 2

    def never(*args, **kwargs):
        pytest.fail("evaluated")

    monkeypatch.setattr(runner, "evaluate_sets", never)
    monkeypatch.setattr(runner, "evaluate_baseline", never)
    cli.main(["tiny", "--stored-seeds", "--no-evaluate", *where])
    out = capsys.readouterr().out
    assert not trained_runs(out.splitlines()) and "evaluating" not in out
    summary = json.loads((store / "cpu" / "tiny.json").read_text())
    a, b = summary["variants"]["a"], summary["variants"]["b"]
    assert a["eval"]["train"]["eval_seed"] == [0, 0]
    assert a["eval"]["train"]["success_rate"] == from_store[0]["variants"]["a"]["eval"]["train"]["success_rate"]
    assert a["eval_greedy"]["train"]["success_rate"] == [None, None]
    assert b["eval"]["train"]["eval_seed"] == [7, 1001] and b["eval_greedy"]["train"]["eval_seed"] == [1000, 1001]
    assert summary["baselines"]["random"]["train"]["seed"] == 0 and summary["baselines"]["oracle"]["train"]["seed"] == 999
    text = (tmp_path / "docs" / "results.md").read_text()
    assert ("sampled policy, evaluations that differ (asked for: 2 episodes, seed 1000 + the run's seed): a, training "
            "houses: seeds 0, 1 2 episodes, seed 0; b, training houses: seed 0 2 episodes, seed 7, seed 1 2 episodes, "
            "seed 1000 + the run's seed; a again, training houses: seeds 0, 1 2 episodes, seed 0") in text
    assert ("greedy policy: 2 episodes per run and house set, seed 1000 + the run's seed; 4 of 6 evaluations "
            "(runs x house sets) not stored, left out") in text
    assert ("baselines, evaluations that differ (asked for: 2 episodes, seed 999): uniformly random policy, training "
            "houses: 2 episodes, seed 0; shortest-path oracle, training houses: 2 episodes, seed 999") in text
    assert "| a | greedy | – | – | – |" in text
