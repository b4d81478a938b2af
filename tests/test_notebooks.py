"""The notebooks run top to bottom: quickstart.ipynb trains a tiny agent, plots, evaluates
and writes a video; evaluate.ipynb restores that run and draws its predictions and path.

Each notebook's "parameters" cell is replaced by tiny settings; the rest runs as shipped,
in a Jupyter kernel (nbclient).
"""

from __future__ import annotations

from pathlib import Path

import nbclient
import nbformat
import pytest

from tiny import TINY_LEARNER

ROOT = Path(__file__).resolve().parents[1]
TINY = TINY_LEARNER + ["env.scene.num_scenes=1", "env.max_episode_steps=12", "train.log_every=1"]


def execute(name: str, parameters: str, cwd: Path):
    book = nbformat.read(ROOT / "notebooks" / name, as_version=4)
    cells = [c for c in book.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(cells) == 1, f"{name} needs exactly one cell tagged 'parameters'"
    cells[0].source = parameters
    nbclient.NotebookClient(book, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}).execute()
    return book


def outputs(book, kind: str) -> list:
    return [o for c in book.cells if c.cell_type == "code" for o in c.get("outputs", []) if kind in o.get("data", {})]


def text(book) -> str:
    parts = []
    for c in book.cells:
        for o in c.get("outputs", []) if c.cell_type == "code" else []:
            parts.append(o.get("text", "") or o.get("data", {}).get("text/plain", ""))
    return "\n".join(parts)


@pytest.fixture(scope="module")
def quickstart(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("notebook")
    workdir = cwd / "run"
    book = execute("quickstart.ipynb", f"""from pathlib import Path
CONFIG = {str(ROOT / "configs" / "quickstart.yaml")!r}
WORKDIR = Path({str(workdir)!r})
UPDATES = 3
OVERRIDES = {TINY!r}
EPISODES = 4
EVAL_HOUSES = ("held-out",)""", cwd)
    return book, workdir


def test_quickstart_notebook_trains_plots_evaluates_and_shows_a_video(quickstart):
    book, workdir = quickstart
    assert (workdir / "metrics.jsonl").read_text().count("\n") == 3
    import imageio.v3 as iio
    import numpy as np

    curve = iio.imread(workdir / "curve.png")  # the notebook's learning curves: lines on axes, not a blank image
    assert curve.ndim == 3 and len(np.unique(curve.reshape(-1, curve.shape[-1]), axis=0)) > 20
    frames = iio.imread(workdir / "episodes.gif", index=None)  # the evaluated episodes, frame by frame
    assert frames.shape[0] > 1 and any(not np.array_equal(frames[0], f) for f in frames[1:])
    assert len(outputs(book, "image/png")) >= 1 and len(outputs(book, "image/gif")) == 1
    table = text(book)
    for policy in ("sample", "random"):
        assert any(line.split()[:2] == ["held-out", policy] for line in table.splitlines())


def test_evaluate_notebook_restores_and_draws(quickstart, tmp_path):
    _, workdir = quickstart
    book = execute("evaluate.ipynb", f"""from pathlib import Path
WORKDIR = Path({str(workdir)!r})
STEP = None
HOUSES = "new-targets"
EPISODES = 4
RECORD_STEPS = 30""", tmp_path)
    out = text(book)
    assert "update 3, 48 training frames" in out and "checkpoints (updates): [0, 3]" in out
    assert "trained  success" in out and "random   success" in out
    assert "episode(s) recorded" in out
    # Predictions: one figure per shown step (1 to 3); the path maps: one more.
    assert 2 <= len(outputs(book, "image/png")) <= 4
