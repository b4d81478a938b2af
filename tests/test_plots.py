"""`python -m a2catvn_jax.plots`: curves of any logged column, and one-line errors for
what cannot be plotted."""

from __future__ import annotations

import json

import pytest
from matplotlib.image import imread

from a2catvn_jax import plots
from a2catvn_jax.run.plots import plot_runs


def _run(path, scale):
    path.mkdir()
    rows = [{"update": u, "frames": 320 * u, "success_rate": 0.1 * scale * u, "episode_length": 100 - u,
             "spl": 0.01 * u, **({"grad_norm/actor": 0.01 * u, "grad_norm/reward_prediction": scale * u}
                                 if u % 2 == 0 else {})} for u in range(1, 9)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(path)


def test_curves_of_default_and_logged_columns(tmp_path, capsys):
    runs = [_run(tmp_path / "a", 1.0), _run(tmp_path / "b", 2.0)]
    out = tmp_path / "curves.png"
    plots.main([*runs, "--out", str(out)])
    wide = imread(out)
    assert "wrote" in capsys.readouterr().out
    # Columns only some rows have (the gradient norms of every 2nd log row), on log axes:
    # one panel each, so a narrower figure than the default three panels.
    plots.main([*runs, "--out", str(out), "--metrics", "grad_norm/actor", "grad_norm/reward_prediction", "--log-y"])
    narrow = imread(out)
    assert narrow.shape[0] == wide.shape[0] and narrow.shape[1] < wide.shape[1]


@pytest.mark.parametrize("args, message", [
    (["--metrics", "grad_norm/depth"], "no run logs 'grad_norm/depth'; the runs' columns: episode_length, frames, "),
    (["--smooth", "0"], "--smooth must be >= 1, got 0"),
])
def test_what_cannot_be_plotted_is_a_one_line_error(tmp_path, capsys, args, message):
    run = _run(tmp_path / "a", 1.0)
    with pytest.raises(SystemExit) as exit_info:
        plots.main([run, "--out", str(tmp_path / "x.png"), *args])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert message in error and error.startswith("python -m a2catvn_jax.plots: error: ")
    assert not (tmp_path / "x.png").exists()


def test_a_directory_without_a_log_is_an_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        plots.main([str(tmp_path), "--out", str(tmp_path / "x.png")])
    assert f"{tmp_path}: no metrics.jsonl" in capsys.readouterr().err


def test_evaluations_during_training_are_drawn_as_measured(tmp_path):
    """A column of eval.jsonl (`train.eval`) is a metric too, drawn unsmoothed at the
    frames of each evaluation, beside a training column (smoothed) of the same run."""
    run = _run(tmp_path / "a", 1.0)
    rows = [{"update": u, "frames": 320 * u, "held-out/sample/success_rate": s} for u, s in ((4, 0.2), (8, 0.5))]
    (tmp_path / "a" / "eval.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "held_out.png"
    plots.main([run, "--out", str(out), "--metrics", "success_rate", "held-out/sample/success_rate"])
    fig = plot_runs([run], out, ["success_rate", "held-out/sample/success_rate"], window=2)
    trained, held_out = (ax.lines[0] for ax in fig.axes)
    assert list(held_out.get_xdata()) == [1280, 2560] and list(held_out.get_ydata()) == [0.2, 0.5]
    assert len(trained.get_xdata()) == 8 and trained.get_ydata()[1] == pytest.approx((0.1 + 0.2) / 2)
