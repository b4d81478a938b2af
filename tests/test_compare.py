"""Comparing variants of different experiments from their stored summaries
(`study.compare`, `experiments --compare`): the numbers against NumPy and SciPy on a
hand-made store, and a clear one-line error for each thing that can be missing."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from a2catvn_jax import experiments as cli
from a2catvn_jax.study import compare
from a2catvn_jax.study.formats import format_estimate

GRAD_NORMS = {  # per variant, per run: the logged gradient norms
    "slow": [[0.6, 0.7, 0.4, 0.9], [0.8, 0.3, 0.55, 1.2]],
    "fast": [[2.0, 3.5, 1.5], [45.0, 2.5, 3.0, 2.2], [1.0, 1.1]],
}
CLIPS = {"slow": 0.5, "fast": 40.0}


def write_store(root, threshold_b=0.5, frames_max_b=3e6):
    """Experiment "ea" with variants "slow" (2 runs, one never reaches the threshold) and
    "other: b" (2 runs, one without gradient norms in its log); experiment "eb" with
    "fast" (3 runs, each with a held-out evaluation)."""
    def entry(name, seeds, frames, final, train, held_out=None, frames_max=3e6):
        runs = []
        for seed, norms in zip(seeds, GRAD_NORMS.get(name, [[1.0, 0.2], []])):
            rel = f"cpu/image_goals/{name.replace(':', '').replace(' ', '_')}/seed_{seed}"
            (root / rel).mkdir(parents=True)
            (root / rel / "metrics.jsonl").write_text(
                "".join(json.dumps({"frames": 8 * (i + 1), "grad_norm": g}) + "\n" for i, g in enumerate(norms)))
            (root / rel / "config.yaml").write_text(f"train:\n  max_grad_norm: {CLIPS.get(name, 0.5)}\n")
            runs.append(rel)
        ev = {"train": {"success_rate": train, "spl": train}}
        if held_out:
            ev["held-out"] = {"success_rate": held_out, "spl": held_out}
        return {"seeds": seeds, "runs": runs, "frames_to_threshold": frames, "frames_max": frames_max,
                "final_success": final, "eval": ev}

    (root / "cpu").mkdir(parents=True)
    (root / "cpu" / "ea.json").write_text(json.dumps({"threshold": 0.5, "variants": {
        "slow": entry("slow", [0, 1], [2.1e6, None], [0.6, 0.3], [0.62, 0.35]),
        "other: b": entry("other: b", [0, 1], [1e6, 1.2e6], [0.9, 0.8], [0.9, 0.85])}}))
    (root / "cpu" / "eb.json").write_text(json.dumps({"threshold": threshold_b, "variants": {
        "fast": entry("fast", [0, 1, 2], [1.1e6, 0.9e6, 1.6e6], [0.95, 0.97, 0.9], [0.96, 1.0, 0.9],
                      held_out=[0.2, 0.3, 0.25], frames_max=frames_max_b)}}))


def rows_of(text, first_cell):
    return [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()
            if line.startswith(f"| {first_cell} |")]


def test_numbers_match_numpy_and_scipy(tmp_path):
    write_store(tmp_path)
    text = compare.compare(["ea:slow", "eb:fast"], "cpu", tmp_path)
    slow, = rows_of(text, "slow")
    fast, = rows_of(text, "fast")
    assert slow[:5] == ["slow", "ea", "0, 1", "2.1M, 1/2 reached; 1 not by 3.0M",
                        format_estimate([0.6, 0.3])]
    assert fast[2] == "0–2" and fast[3].endswith("3/3 reached")
    assert slow[6] == "–"  # "slow" has no held-out evaluation
    # Gradient norms: the range of the runs' medians, of all log rows, and the rows above each run's clip.
    medians = [np.median(g) for g in GRAD_NORMS["fast"]]
    assert fast[-2] == f"{min(medians):.2f}–{max(medians):.2f}; 1.00–45.00"
    assert fast[-1] == "1/9 (clip 40)"
    assert slow[-1] == f"{sum(x > 0.5 for g in GRAD_NORMS['slow'] for x in g)}/8 (clip 0.5)"
    assert "each log row holds its mean over 10 updates" in text  # the default train.log_every
    assert "differ in length" not in text
    # Welch's tests against the first variant; frames to threshold count a run that never reaches it at 3M.
    head = next(line for line in text.splitlines() if line.startswith("| Welch's p"))
    assert "against slow (ea)" in head and "success, held-out houses" not in head  # only sets both have
    p = rows_of(text, "fast (eb)")[0][1:]
    expected = [stats.ttest_ind(a, b, equal_var=False).pvalue for a, b in (
        ([2.1e6, 3e6], [1.1e6, 0.9e6, 1.6e6]), ([0.6, 0.3], [0.95, 0.97, 0.9]), ([0.62, 0.35], [0.96, 1.0, 0.9]))]
    assert p == [f"{x:.2g}" for x in expected]


def test_the_command_line_prints_the_comparison(tmp_path, capsys):
    write_store(tmp_path)
    cli.main(["--compare", "ea:slow", "ea:other: b", "eb:fast", "--store", str(tmp_path)])
    out = capsys.readouterr().out
    assert len(rows_of(out, "other: b (ea)")) == 1 and len(rows_of(out, "fast (eb)")) == 1
    # A run whose log has no gradient norm is left out of the norms and counted as such.
    other, = rows_of(out, "other: b")
    assert other[-2:] == ["0.60; 0.20–1.00 (1 of 2 runs log it)", "1/2 (clip 0.5)"]


def test_runs_of_different_lengths_are_noted(tmp_path):
    write_store(tmp_path, frames_max_b=5e6)
    text = compare.compare(["ea:slow", "eb:fast"], "cpu", tmp_path)
    assert "The runs differ in length (slow (ea) 3.0M, fast (eb) 5.0M frames)" in text


def test_the_episodes_the_numbers_rest_on_are_noted(tmp_path):
    """A report that fell back on stored evaluations records the episodes its numbers rest
    on ("episodes_used") beside those asked for ("episodes"); the comparison goes by the former."""
    write_store(tmp_path)
    for name, asked, used in (("ea", 500, [100]), ("eb", 500, [500])):
        path = tmp_path / "cpu" / f"{name}.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "episodes": asked, "episodes_used": used}))
    text = compare.compare(["ea:slow", "eb:fast"], "cpu", tmp_path)
    assert "over different numbers of episodes (ea: 100, eb: 500)" in text
    path = tmp_path / "cpu" / "ea.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "episodes_used": [500]}))
    assert "different numbers of episodes" not in compare.compare(["ea:slow", "eb:fast"], "cpu", tmp_path)


@pytest.mark.parametrize("args, message", [
    (["ea:slow"], "at least two variants"),
    (["ea:slow", "eb"], "name a variant as EXPERIMENT:LABEL"),
    (["ea:slow", "nowhere:x"], "no stored summary of 'nowhere'"),
    (["ea:slow", "ea:fast"], "ea has no reported variant 'fast'; its variants: 'slow', 'other: b'"),
    (["ea:slow", "eb:fast", "--scale", "paper"], "no stored summary of 'ea' at paper scale"),
    (["aux:A2C", "ea:slow", "--scale", "paper"], "report it first: python -m a2catvn_jax.experiments aux "
                                                 "--stored-seeds --no-evaluate --scale paper --store"),
    (["ea:slow", "eb:fast", "--no-evaluate"], "it takes no --no-evaluate"),
    (["ea:slow", "eb:fast", "--threshold", "0.9"], "it takes no --threshold"),
    (["ea:slow", "eb:fast", "--seeds", "0", "--set", "seed=1"], "it takes no --seeds, --set"),
    (["ea:slow", "eb:fast", "--stored-seeds"], "it takes no --stored-seeds"),
    (["aux", "--compare", "ea:slow", "eb:fast"], "it takes no NAME"),
    (["ea:slow", "ea:broken"], "broken/seed_0 cannot be read"),
    (["ea:slow", "ec:x"], "ec.json is not an experiment summary as the runner writes it: no numeric 'threshold'"),
    (["ea:slow", "ed:x"], "ed.json is not an experiment summary as the runner writes it: variant 'x' lacks runs, eval"),
    (["ea:slow", "ee:x"], "ee.json is not an experiment summary as the runner writes it: no 'variants' mapping"),
])
def test_bad_comparisons_are_one_line_errors(tmp_path, capsys, args, message):
    write_store(tmp_path)
    summary = json.loads((tmp_path / "cpu" / "ea.json").read_text())
    summary["variants"]["broken"] = {**summary["variants"]["slow"], "runs": ["cpu/image_goals/broken/seed_0"]}
    (tmp_path / "cpu/image_goals/broken/seed_0").mkdir(parents=True)
    (tmp_path / "cpu/image_goals/broken/seed_0/metrics.jsonl").write_text('{"grad_norm": "abc"}\n')
    (tmp_path / "cpu" / "ea.json").write_text(json.dumps(summary))
    entry = {k: summary["variants"]["slow"][k] for k in ("seeds", "frames_to_threshold", "frames_max", "final_success")}
    (tmp_path / "cpu" / "ec.json").write_text(json.dumps({"variants": {"x": summary["variants"]["slow"]}}))
    (tmp_path / "cpu" / "ed.json").write_text(json.dumps({"threshold": 0.5, "variants": {"x": entry}}))
    (tmp_path / "cpu" / "ee.json").write_text(json.dumps([1, 2]))
    if args[0] != "aux":
        args = ["--compare", *args]
    with pytest.raises(SystemExit) as exit_:
        cli.main([*args, "--store", str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in err and "Traceback" not in err


def test_different_thresholds_and_unreadable_runs_are_refused(tmp_path):
    write_store(tmp_path, threshold_b=0.7)
    with pytest.raises(compare.CompareError, match="different success thresholds"):
        compare.load_variants(["ea:slow", "eb:fast"], "cpu", tmp_path)
    (tmp_path / "cpu" / "image_goals" / "other_b" / "seed_1" / "metrics.jsonl").unlink()
    with pytest.raises(compare.CompareError, match="other_b/seed_1 cannot be read"):
        compare.compare(["ea:slow", "ea:other: b"], "cpu", tmp_path)
    (tmp_path / "cpu" / "ea.json").write_text("{not json")
    with pytest.raises(compare.CompareError, match="ea.json cannot be read as an experiment summary"):
        compare.compare(["ea:slow", "ea:other: b"], "cpu", tmp_path)
