"""The experiment runner: run naming and sharing, statistics, the report, and a tiny
end-to-end experiment that trains, evaluates, stores, plots and writes its section;
then, with the work directories deleted, re-tabulates from the store alone, refuses an
evaluation that needs a checkpoint, and trains only an added seed."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from a2catvn_jax import experiments as cli
from a2catvn_jax.config import load_config, save_config
from a2catvn_jax.errors import Interrupted
from a2catvn_jax.run import compare
from a2catvn_jax.run import experiments as ex
from tiny import TINY_LEARNER

# Plain A2C (no auxiliary loss, no replay): the smallest training program to compile.
TINY = TINY_LEARNER + list(ex.NO_VN + ex.NO_UNREAL) + [
    "env.max_episode_steps=10", "train.total_frames=32", "train.log_every=1", "train.checkpoint_every=1"]


def test_every_experiment_has_both_configs_and_plans():
    for exp in ex.EXPERIMENTS.values():
        for scale in ex.SCALES:
            runs = ex.plan(exp, scale, [0, 1], "/tmp/unused", store="/tmp/store")
            assert len(runs) == 2 * len(exp.variants)
            assert {r.cfg.seed for r in runs} == {0, 1}
            # Variants differ in their configuration (or pre-training), so in their work directory.
            assert len({r.workdir.parent for r in runs}) == len(exp.variants)
            assert all(r.stored.relative_to("/tmp/store") == r.workdir.relative_to("/tmp/unused") for r in runs)


def test_every_experiment_has_the_blind_control_of_its_task():
    # The configured agent on images of zeros, in every experiment: the same run (so the
    # same work directory) wherever two experiments share a task.
    blind_dirs = {}
    for exp in ex.EXPERIMENTS.values():
        for scale in ex.SCALES:
            controls = [r for r in ex.plan(exp, scale, [0], "/r") if r.cfg.agent.blind]
            assert [r.variant for r in controls] == [ex.BLIND_CONTROL], exp.name
            path = exp.config_path(scale)
            assert controls[0].cfg == ex.load_config(path, ["seed=0", "agent.blind=true"])
            assert blind_dirs.setdefault((scale, path), controls[0].workdir) == controls[0].workdir


def test_the_authors_variants_are_the_preset_and_the_documented_settings():
    # The network variant is configs/presets/authors_network.yaml (padded for 32 px), the
    # loss variant the `--set` line of docs/method.md, so the experiment follows both.
    quickstart = ex.CONFIGS / "quickstart.yaml"
    preset = ex.CONFIGS / "presets" / "authors_network.yaml"
    assert ex.load_config(quickstart, ex.AUTHORS_NETWORK) == ex.load_config([quickstart, preset],
                                                                            ["agent.conv_padding=same"])
    method = (Path(__file__).parents[1] / "docs" / "method.md").read_text()
    documented = method.split("The authors' loss settings in one line")[1].split("```")[1]
    assert documented.replace("--set", " ").replace("\\", " ").split() == list(ex.AUTHORS_LOSSES)
    labels = [v.label for v in ex.EXPERIMENTS["authors"].variants]
    assert labels[0] == "A2CAT-VN" and ex.EXPERIMENTS["authors"].variants[0] == ex.EXPERIMENTS["sight"].variants[0]
    assert len(labels) == 4


def test_learning_by_sight_experiments():
    aux, ablations, gen = (ex.EXPERIMENTS[n] for n in ("aux", "ablations", "generalisation"))
    assert [v.label for v in aux.variants] == ["A2CAT-VN (pre-trained)", "A2CAT-VN", "A2C+UNREAL", "A2C",
                                               "blind A2CAT-VN"]
    for exp in (aux, gen):
        blind = [r for r in ex.plan(exp, "cpu", [0], "/r") if r.variant.label == "blind A2CAT-VN"]
        assert len(blind) == 1 and blind[0].cfg.agent.blind
    runs = ex.plan(ablations, "cpu", [0], "/r")
    assert runs[0].workdir == ex.plan(aux, "cpu", [0], "/r")[1].workdir  # the full A2CAT-VN is shared
    weights = ex.AUX_LOSSES
    for run, loss in zip(runs[1:-2], weights, strict=True):
        w = run.cfg.train.loss_weights
        assert getattr(w, loss) == 0 and all(getattr(w, other) > 0 for other in weights if other != loss)
    # Then all three visual-navigation losses at once and the blind control: the aux experiment's runs.
    assert [r.workdir for r in runs[-2:]] == [r.workdir for r in ex.plan(aux, "cpu", [0], "/r")[2::2]]
    assert aux.threshold_at("cpu") == ablations.threshold_at("cpu") == gen.threshold_at("cpu") == 0.5
    sight = ex.EXPERIMENTS["sight"]
    assert sight.config_path("cpu") == sight.config_path("paper") == ex.CONFIGS / "quickstart.yaml"
    seeing, blind = ex.plan(sight, "cpu", [0], "/r")
    assert not seeing.cfg.agent.blind and blind.cfg.agent.blind
    assert seeing.cfg == ex.load_config(ex.CONFIGS / "quickstart.yaml", ["seed=0"])
    aux_qs = ex.EXPERIMENTS["aux_quickstart"]
    runs = {r.variant.label: r for r in ex.plan(aux_qs, "cpu", [0], "/r")}
    assert runs["A2CAT-VN"].workdir == seeing.workdir  # shares the sight experiment's runs
    assert runs["A2CAT-VN (pre-trained)"].variant.pretrain and runs["A2CAT-VN (pre-trained)"].cfg.pretrain.epochs == 10
    assert runs["A2C"].cfg.train.loss_weights.reward_prediction == 0 and runs["A2C+UNREAL"].cfg.train.loss_weights.depth == 0
    assert runs["A2C+UNREAL"].cfg.train.loss_weights.pixel_control > 0
    abl_qs = ex.plan(ex.EXPERIMENTS["ablations_quickstart"], "cpu", [0], "/r")
    assert abl_qs[0].workdir == seeing.workdir and len(abl_qs) == 3 + len(weights)  # the full A2CAT-VN is sight's
    for run, loss in zip(abl_qs[1:-2], weights, strict=True):
        w = run.cfg.train.loss_weights
        assert getattr(w, loss) == 0 and all(getattr(w, other) > 0 for other in weights if other != loss)
        assert run.cfg.env == seeing.cfg.env
    assert [r.workdir for r in abl_qs[-2:]] == [runs["A2C+UNREAL"].workdir, blind.workdir]  # stored already
    # the stored seeds and the listing look for its runs under the same single configuration
    assert ex.stored_seeds(sight, "cpu", "/nonexistent") == {"A2CAT-VN": [], "blind A2CAT-VN": []}
    assert "(configs/quickstart.yaml;" in ex.listing("/nonexistent", names=["sight"])


def test_shared_variants_share_runs_and_seeds_do_not(tmp_path):
    """Run keys alone (an empty store: no run stored under an older key)."""
    store = tmp_path / "store"
    aux, curriculum = ex.EXPERIMENTS["aux"], ex.EXPERIMENTS["curriculum"]
    pre, a = ex.plan(aux, "cpu", [0], "/r", store=store)[:2]
    c = ex.plan(curriculum, "cpu", [0], "/r", store=store)
    assert c[1].workdir == a.workdir  # the CPU task is configured with its curriculum
    assert c[0].workdir != a.workdir and not c[0].cfg.train.curriculum
    paper = ex.plan(curriculum, "paper", [0], "/r", store=store)
    assert paper[0].workdir == ex.plan(aux, "paper", [0], "/r", store=store)[1].workdir  # the paper-sized one without
    assert pre.workdir != a.workdir and pre.cfg == a.cfg  # same config, pre-trained: another run
    assert ex.plan(ex.EXPERIMENTS["pretraining"], "cpu", [0], "/r", store=store)[1].workdir == pre.workdir
    s0, s1 = ex.plan(aux, "cpu", [0, 1], "/r", store=store)[:2]
    assert s0.workdir.parent == s1.workdir.parent and s0.workdir != s1.workdir


def test_the_clip_40_comparison_shares_runs_and_keeps_every_loss(tmp_path):
    store = tmp_path / "store"
    runs = {r.variant.label: r for r in ex.plan(ex.EXPERIMENTS["aux_clip40"], "cpu", [0], "/r", store=store)}
    clipping = {r.variant.label: r for r in ex.plan(ex.EXPERIMENTS["clipping"], "cpu", [0], "/r", store=store)}
    aux = {r.variant.label: r for r in ex.plan(ex.EXPERIMENTS["aux"], "cpu", [0], "/r", store=store)}
    assert runs["A2CAT-VN, clip 40"].workdir == clipping["A2CAT-VN, clip 40"].workdir
    assert runs["A2C"].workdir == aux["A2C"].workdir and runs["blind A2CAT-VN"].workdir == aux["blind A2CAT-VN"].workdir
    pre, unreal = runs["A2CAT-VN (pre-trained), clip 40"], runs["A2C+UNREAL, clip 40"]
    assert pre.variant.pretrain and pre.cfg == runs["A2CAT-VN, clip 40"].cfg
    assert pre.workdir not in (runs["A2CAT-VN, clip 40"].workdir, aux["A2CAT-VN (pre-trained)"].workdir)
    assert pre.cfg.train.max_grad_norm == unreal.cfg.train.max_grad_norm == 40
    assert unreal.cfg.train.loss_weights == aux["A2C+UNREAL"].cfg.train.loss_weights
    w = pre.cfg.train.loss_weights
    assert all(getattr(w, loss) > 0 for loss in ex.AUX_LOSSES)
    assert aux["A2CAT-VN"].cfg.train.max_grad_norm == 0.5


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
    np.testing.assert_allclose(ex.smooth(np.array([1.0, np.nan, 3.0, 5.0]), 2), [1.0, 1.0, 3.0, 4.0])
    curve = {"frames": np.array([10.0, 20.0, 30.0]), "success_rate": np.array([0.2, 0.75, 0.6])}
    assert ex.frames_to_threshold(curve, 0.7) == 20.0
    assert ex.frames_to_threshold(curve, 0.8) is None
    # 20 rows: the last 10% is rows 18-19, the 10% before it rows 16-17; None and NaN rows left out
    rows = [{"success_rate": 0.1}] * 16 + [{"success_rate": 0.4}, {"success_rate": 0.6},
                                           {"success_rate": 0.7}, {"success_rate": None}]
    assert ex.final_success(rows) == pytest.approx(0.7)
    assert ex.late_change(rows) == pytest.approx(0.7 - 0.5)
    assert ex.late_change(rows[:12] + rows[-4:][::-1]) == pytest.approx(0.5 - 0.7)  # 16 rows: the last 2 vs the 2 before
    assert math.isnan(ex.late_change(rows[:1]))
    assert ex.format_estimate([0.05, -0.01, 0.03], -1.0, 1.0, "{:+.2f}".format) == "+0.02 [-0.05, +0.10]"


def test_t_interval_by_hand():
    # 0.5 .. 0.9: mean 0.7, sample sd sqrt(0.1 / 4), standard error sd / sqrt(5) = 0.0707107;
    # t quantile 0.975 with 4 degrees of freedom (tables): 2.776445.
    est = ex.estimate([0.5, 0.6, 0.7, 0.8, 0.9])
    half = 2.776445 * math.sqrt(0.1 / 4) / math.sqrt(5)
    assert est.n == 5 and est.mean == pytest.approx(0.7)
    assert est.low == pytest.approx(0.7 - half, abs=1e-6) and est.high == pytest.approx(0.7 + half, abs=1e-6)
    assert ex.format_estimate([0.5, 0.6, 0.7, 0.8, 0.9]) == "0.70 [0.50, 0.90]"
    # clipped to the possible range; one value: no interval; missing values are counted
    assert ex.format_estimate([0.9, 1.0]) == "0.95 [0.31, 1.00]"
    assert ex.format_estimate([0.25]) == "0.25"
    assert ex.format_estimate([0.5, None, 0.7, math.nan]) == "0.60 [0.00, 1.00] (n=2)"
    assert ex.format_estimate([None, None]) == "–"


def test_frames_to_threshold_formatting():
    # reached: 400k, 500k; t(0.975, 1) = 12.706 x standard error 50k: [-185k, 1085k], clipped at 0
    assert ex.format_frames([400e3, None, 500e3], 2e6) == "450k [0, 1.1M], 2/3 reached; 1 not by 2.0M"
    assert ex.format_frames([300e3, 300e3], 4e5) == "300k [300k, 300k], 2/2 reached"
    assert ex.format_frames([300e3], 4e5) == "300k, 1/1 reached"
    assert ex.format_frames([None, None, None], 4e5) == "0/3 reached by 400k"
    p = ex.welch_p([100.0, 110.0, 120.0], [400.0, 400.0, 390.0])
    assert p == pytest.approx(stats.ttest_ind([100, 110, 120], [400, 400, 390], equal_var=False).pvalue)
    assert ex.welch_p([1.0], [2.0, 3.0]) is None and ex.welch_p([4.0, 4.0], [4.0, 4.0]) is None


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


def test_trimmed_log_keeps_the_resumed_rows_and_few_bytes(tmp_path):
    row = {"update": 0, "frames": 0, "fps": 1234.5678, "loss/actor": 0.0123456789, "success_rate": 0.30645161290322,
           "episode_length": 92.48387096774194, "spl": math.nan, "episodes": 62}
    rows = [{**row, "update": u, "frames": 320 * u} for u in (20, 40, 60, 40, 60, 80)]  # resumed at 40
    trimmed = ex.trim_log(rows)
    assert [r["update"] for r in trimmed] == [20, 40, 60, 80]
    assert set(trimmed[0]) <= set(ex.STORED_COLUMNS) and "fps" not in trimmed[0]
    assert trimmed[0]["success_rate"] == 0.3065 and math.isnan(trimmed[0]["spl"])


# "b" differs from "a" only in bookkeeping, so it has its own runs but shares the compiled programs.
TINY_VARIANTS = (ex.Variant("a"), ex.Variant("b", ("train.keep_checkpoints=2",)), ex.Variant("a again"))


def tiny(variants=TINY_VARIANTS, name="tiny"):
    return ex.Experiment(name, "tiny comparison", "image_goals", variants, threshold=0.9, cpu_threshold=0.5,
                         evaluations=("train",))


def run_tiny(root, exp=None, seeds=(0, 1), episodes=2, **kw):
    lines = []
    summary = ex.run_experiment(exp or tiny(), scale="cpu", seeds=seeds, episodes=episodes, root=root / "runs",
                                docs=root / "docs", overrides=TINY, command="tiny", compilation_cache=False,
                                log=lines.append, **kw)
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
    stopped = next(r for r in ex.plan(tiny(), "cpu", [0], root / "runs", TINY) if r.variant.label == "b")
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
    store = root / "docs" / "experiments" / "runs"
    for rel in a["runs"] + summary["variants"]["b"]["runs"]:
        d = store / rel
        assert {p.name for p in d.iterdir()} == {"config.yaml", "variant.json", "metrics.jsonl", "eval_train_sample_2.json",
                                                 "experiment_time.json", "done.json"}
        done = json.loads((d / "done.json").read_text())
        assert done["updates"] == 2 and done["frames"] == 32 and done["machine"] and done["date"]
        assert set(json.loads((d / "metrics.jsonl").read_text().splitlines()[0])) <= set(ex.STORED_COLUMNS)
    baselines = {p.name.rsplit("_", 1)[0] for p in (store / "cpu" / "image_goals" / "baselines").iterdir()}
    assert baselines == {"random_train_2", "oracle_train_2"}
    assert json.loads((store / "cpu" / "tiny.json").read_text())["variants"]["b"]["eval"] == summary["variants"]["b"]["eval"]
    assert (root / "docs" / "experiments" / "tiny_cpu.png").stat().st_size > 0
    assert "<!-- experiment tiny cpu -->" in text and "| b |" in text
    assert "| uniformly random policy | – | – |" in text and "| shortest-path oracle | – | – |" in text
    assert "95% t-interval" in text and "Seeds: 0, 1 (2 runs per variant)" in text


def test_listing_counts_stored_seeds(trained, monkeypatch, capsys):
    root = trained[0]
    monkeypatch.setitem(ex.EXPERIMENTS, "tiny", tiny())
    cli.main(["--list", "tiny", "--scale", "cpu", "--docs", str(root / "docs"), "--set", *TINY])
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
    with pytest.raises(ex.ExperimentError, match=r"a, seed 0 .*eval_train_sample_2.json.*final checkpoint"):
        run_tiny(root, episodes=3)
    monkeypatch.setitem(ex.EXPERIMENTS, "tiny", tiny())
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["tiny", "--seeds", "0", "1", "--episodes", "3", "--docs", str(root / "docs"), "--root",
                  str(root / "runs"), "--set", *TINY])
    assert exit_info.value.code == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and errors[0].startswith("error: a, seed 0 (")
    summary, lines = run_tiny(root, episodes=3, skip_missing=True)
    assert summary["variants"]["a"]["eval"]["train"]["success_rate"] == [None, None]
    assert any(line.startswith("skipped: a, seed 0") for line in lines)
    section = (root / "docs" / "results.md").read_text()
    assert "| a | " in section and "| – | – |" in section
    assert summary["variants"]["a"]["final_success"] == from_store[0]["variants"]["a"]["final_success"]


def test_an_added_seed_trains_only_that_seed(trained, from_store):
    root = trained[0]
    one = tiny((ex.Variant("a"),), name="tiny_a")
    summary, lines = run_tiny(root, one, seeds=(0, 1, 2))
    assert trained_runs(lines) == ["training a, seed 2"]
    assert summary["variants"]["a"]["seeds"] == [0, 1, 2] and len(summary["variants"]["a"]["eval"]["train"]["spl"]) == 3
    assert "3 runs per variant" in (root / "docs" / "results.md").read_text()
    assert ex.stored_seeds(one, "cpu", root / "docs" / "experiments" / "runs", TINY) == {"a": [0, 1, 2]}


def test_all_stored_reports_each_variants_stored_runs_part_way(trained, from_store, monkeypatch, capsys):
    root = trained[0]
    run_tiny(root, tiny((ex.Variant("a"),), name="tiny_a"), seeds=(0, 1, 2))  # "a" has seed 2 stored, "b" not
    monkeypatch.setitem(ex.EXPERIMENTS, "tiny", tiny())
    where = ["--episodes", "2", "--docs", str(root / "docs"), "--root", str(root / "nowhere"), "--set", *TINY]
    cli.main(["tiny", "--all-stored", *where])
    assert not trained_runs(capsys.readouterr().out.splitlines())
    summary = json.loads((root / "docs" / "experiments" / "runs" / "cpu" / "tiny.json").read_text())
    assert [summary["variants"][v]["seeds"] for v in ("a", "b", "a again")] == [[0, 1, 2], [0, 1], [0, 1, 2]]
    assert len(summary["variants"]["a"]["eval"]["train"]["success_rate"]) == 3
    text = (root / "docs" / "results.md").read_text()
    assert "Seeds: a 0–2 (3); b 0, 1 (2); a again 0–2 (3)." in text
    cli.main(["tiny", "--stored-seeds", *where])  # the seeds stored for every variant
    assert "Seeds: 0, 1 (2 runs per variant)." in (root / "docs" / "results.md").read_text()
    # A variant with no stored run is left out of the part-way report and named in it ...
    c = ex.Variant("c", ("train.max_grad_norm=1",))
    monkeypatch.setitem(ex.EXPERIMENTS, "tiny", tiny(TINY_VARIANTS + (c,)))
    capsys.readouterr()
    cli.main(["tiny", "--all-stored", *where])
    assert "left out of this part-way report, none of their runs stored yet: 'c'" in capsys.readouterr().out
    summary = json.loads((root / "docs" / "experiments" / "runs" / "cpu" / "tiny.json").read_text())
    assert list(summary["variants"]) == ["a", "b", "a again"] and summary["not_stored"] == ["c"]
    text = (root / "docs" / "results.md").read_text()
    assert "Not in this part-way report, no run stored yet: c." in text and "| c |" not in text
    # ... but not the first variant, the one the others are compared with: one line that names it.
    monkeypatch.setitem(ex.EXPERIMENTS, "tiny", tiny((c,) + TINY_VARIANTS))
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
    one = tiny((ex.Variant("a"), ex.Variant("a again")), name="tiny_jobs")  # one run per seed, two variants
    monkeypatch.setitem(ex.EXPERIMENTS, one.name, one)
    where = ["--docs", str(root / "docs"), "--root", str(root / "runs"), "--set", *TINY]
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

    monkeypatch.setattr(ex, "run_pool", pool)
    summary, lines = run_tiny(root, one, seeds=(0, 1, 5), jobs=2)
    (commands, jobs, logs), = pools
    assert jobs == 2 and len(commands) == 1 and logs[0].name == "train.log" and logs[0].parent.name == "seed_5"
    assert "started a, seed 5 on core(s) 0; log: " + str(logs[0]) in lines
    assert any(line.startswith("stored: a, seed 5 (") for line in lines)
    assert summary["variants"]["a"]["seeds"] == summary["variants"]["a again"]["seeds"] == [0, 1, 5]
    assert "training a, seed 5" in capsys.readouterr().out  # the process's own output
    # a process that fails is named with its log, and nothing is reported
    monkeypatch.setattr(ex, "run_pool", lambda commands, jobs, logs, on_start, on_end: [1] * len(commands))
    with pytest.raises(ex.ExperimentError, match=r"1 of 1 run\(s\) failed: a, seed 6 \(log: .*seed_6/train.log\)"):
        run_tiny(root, one, seeds=(0, 6), jobs=2)


def test_an_interrupted_run_stops_the_runner_and_the_same_command_resumes_it(tmp_path, monkeypatch):
    """A run whose training stops early with a checkpoint (what Ctrl-C or SIGTERM does to
    the training loop; here it returns after one of its two updates) is neither evaluated
    nor stored: the runner stops with an error naming it, and the same command resumes it
    from that checkpoint to its end."""
    exp = tiny((ex.Variant("a"),), name="tiny_interrupted")
    real = ex.train
    monkeypatch.setattr(ex, "train", lambda *args, **kw: real(*args, **kw, max_updates=1))
    with pytest.raises(Interrupted, match=r"interrupted: a, seed 0 stopped at update 1 of 2 with a "
                                         r"checkpoint in .*seed_0; the same command resumes it"):
        run_tiny(tmp_path, exp, seeds=(0,))
    (run,) = ex.plan(exp, "cpu", [0], tmp_path / "runs", TINY, tmp_path / "docs" / "experiments" / "runs")
    assert not run.is_stored()
    monkeypatch.setattr(ex, "train", real)
    summary, lines = run_tiny(tmp_path, exp, seeds=(0,), report=False)
    assert trained_runs(lines) == ["resuming a, seed 0"] and run.is_stored()
    assert summary == {"experiment": "tiny_interrupted", "trained": ["a, seed 0"]}


def test_a_second_ctrl_c_aborts_the_runner_with_one_line(tmp_path, monkeypatch, capsys):
    """A second Ctrl-C while a run trains in the runner's own process (`--jobs 1`) ends the
    command with one line and exit status 130, not a traceback."""
    exp = tiny((ex.Variant("a"),), name="tiny_aborted")
    monkeypatch.setitem(ex.EXPERIMENTS, exp.name, exp)

    def aborted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ex, "train", aborted)
    with pytest.raises(SystemExit) as exit_info:
        cli.main([exp.name, "--seeds", "0", "--docs", str(tmp_path / "docs"), "--root", str(tmp_path / "runs"),
                  "--set", *TINY])
    assert exit_info.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["aborted: the run in training keeps only its last checkpoint; the same command resumes each "
                   "unfinished run from its last checkpoint"]


def test_a_run_stored_before_new_configuration_keys_is_found(trained, from_store, tmp_path):
    store = tmp_path / "store"
    shutil.copytree(trained[0] / "docs" / "experiments" / "runs", store)
    exp = tiny((ex.Variant("a"),))
    primary = ex.plan(exp, "cpu", [0, 1], tmp_path / "runs", TINY, store)
    old = primary[0].stored.parent.rename(primary[0].stored.parent.with_name("0000aaaa"))

    def drop(config, key):
        config.write_text("".join(line for line in config.read_text().splitlines(True)
                                  if not line.strip().startswith(f"{key}:")))

    # seed 0 was stored before train.grad_norm_every existed: its default is the old behaviour
    drop(old / "seed_0" / "config.yaml", "grad_norm_every")
    # seed 1 before env.success_heading_deg: its legacy value (any heading) is another task
    drop(old / "seed_1" / "config.yaml", "grad_norm_every")
    drop(old / "seed_1" / "config.yaml", "success_heading_deg")
    s0, s1 = ex.plan(exp, "cpu", [0, 1], tmp_path / "runs", TINY, store)
    assert s0.is_stored() and s0.stored == old / "seed_0" and s0.workdir == tmp_path / "runs" / s0.relative
    assert s0.relative.split("/")[2] == "0000aaaa"
    assert not s1.is_stored() and s1.stored == primary[1].stored
    seeds = ex.stored_seeds(exp, "cpu", store, TINY)["a"]
    assert 0 in seeds and 1 not in seeds


def test_a_run_in_progress_under_an_older_key_resumes_there(tmp_path):
    """A work directory with a checkpoint and the same configuration under another key
    (started before a configuration key was added) is where the unstored run goes on;
    without a checkpoint, or with another configuration, it is not."""
    store, root = tmp_path / "store", tmp_path / "runs"
    exp = tiny((ex.Variant("a"),))
    primary = ex.plan(exp, "cpu", [0, 1], root, TINY, store)
    assert not primary[0].is_stored()
    for run in primary:
        old = run.workdir.parent.with_name("0000bbbb") / run.workdir.name
        (old / "checkpoints" / "3").mkdir(parents=True)
        (old / "variant.json").write_text(json.dumps({"label": "a", "overrides": [], "pretrain": False}))
        other = ["train.learning_rate=0.0123"] if run.seed == 1 else []
        save_config(load_config(exp.config_path("cpu"), [*TINY, f"seed={run.seed}", *other]), old / "config.yaml")
    s0, s1 = ex.plan(exp, "cpu", [0, 1], root, TINY, store)
    assert s0.workdir == primary[0].workdir.parent.with_name("0000bbbb") / "seed_0"
    assert s0.stored == store / s0.relative and s0.relative.split("/")[2] == "0000bbbb"
    assert s1.workdir == primary[1].workdir  # another configuration: not resumed
    # A checkpoint under the run's own key wins.
    (primary[0].workdir / "checkpoints" / "5").mkdir(parents=True)
    assert ex.plan(exp, "cpu", [0], root, TINY, store)[0].workdir == primary[0].workdir


def test_train_only_some_variants(trained, from_store, monkeypatch):
    """`train_only` trains the named variants' missing runs and reports nothing while
    other variants' runs are missing; an unknown label is an error naming the variants."""
    root = trained[0]
    with pytest.raises(ex.ExperimentError, match=r"tiny has no variant 'c'; its variants: 'a', 'b', 'a again'"):
        run_tiny(root, train_only=["c"])
    monkeypatch.setattr(ex, "train_run", lambda run, log: pytest.fail(f"trained {run.name}"))
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
    store = root / "docs" / "experiments" / "runs"
    text = compare.compare(["tiny:a", "tiny:b"], "cpu", store)
    a, = [line for line in text.splitlines() if line.startswith("| a | tiny | 0, 1 |")]
    norms = [json.loads(line)["grad_norm"] for rel in summary["variants"]["a"]["runs"]
             for line in (store / rel / "metrics.jsonl").read_text().splitlines()]
    assert a.endswith(f"| {sum(g > 0.5 for g in norms)}/{len(norms)} (clip 0.5) |")  # the default clip
    v = summary["variants"]["a"]
    assert f"| {ex.format_frames(v['frames_to_threshold'], v['frames_max'])} | {ex.format_estimate(v['final_success'])} |" in a
    assert "each log row holds one update's" in text  # TINY logs every update
    b, = [line for line in text.splitlines() if line.startswith("| b (tiny) |")]
    p = summary["variants"]["b"]["welch_p_frames_vs_first"]
    assert b.split("|")[2].strip() == ("–" if p is None else f"{p:.2g}")
