"""Evaluation during training (`train.eval`): every `train.eval.every` updates the
parameters of that moment act in the chosen house sets (held-out houses by default)
with each chosen policy, at curriculum complexity 1, for the same episodes each time
(`train.eval.seed`). What it measures is what `evaluate` measures from a checkpoint of
that update with the same houses, policy, episodes and seed, so that a run's curve of
success in unseen houses needs no checkpoint kept per point.

Rows go to eval.jsonl, eval.csv and TensorBoard in the work directory, one per
evaluation: update, frames, and for each house set H and policy P the keys
"H/P/success_rate", "H/P/spl" and "H/P/episode_length". Evaluation reads the
parameters only: the training state, its random keys and so the run itself are the
same with evaluation on or off.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from a2catvn_jax.memo import Memo
from a2catvn_jax.run.evaluation import run_episodes
from a2catvn_jax.run.logger import MetricsWriter, truncate_metrics
from a2catvn_jax.run.restore import Restored, eval_config, make_envs

FIELDS = ("success_rate", "spl", "episode_length")

# The evaluation worlds of the last configuration: the next seed of an experiment in
# this process builds no houses again.
WORLDS = Memo("evaluation-during-training worlds", keep=1)


class TrainingEval:
    """Evaluations of a run at multiples of `train.eval.every` updates (see the module
    docstring). `due(update)` says whether one falls at `update`; calling the object
    with the parameters evaluates them and writes the row. Runs of one process only
(the training loop refuses it in a run of several)."""

    def __init__(self, cfg, networks, workdir: Path, start: int, devices: int, log: Callable[[str], None]):
        self.ec = cfg.train.eval
        self.run_cfg = cfg
        self.cfg = eval_config(cfg)
        self.networks = networks
        self.workdir = Path(workdir)
        self.devices = devices
        self.log = log
        t0 = time.perf_counter()
        self.envs = WORLDS.get((self.cfg.env, self.ec.houses), lambda: make_envs(self.cfg.env, self.ec.houses))
        log(f"evaluation every {self.ec.every} updates: {self.ec.episodes} episodes in "
            f"{', '.join(f'{h} houses' for h in self.ec.houses)} with the {' and '.join(self.ec.policies)} "
            f"polic{'ies' if len(self.ec.policies) > 1 else 'y'} (seed {self.ec.seed}); its worlds built in "
            f"{time.perf_counter() - t0:.1f} s")
        dropped = truncate_metrics(workdir, start, name="eval")
        if dropped:
            log(f"removed {dropped} row(s) after update {start} from {self.workdir / 'eval.jsonl'}: the run "
                f"evaluates again")
        self.writer = MetricsWriter(workdir, name="eval")

    def due(self, update: int) -> bool:
        return update > 0 and update % self.ec.every == 0

    def __call__(self, params, update: int, frames: int) -> dict:
        """Evaluate `params` (the training state's, at `update` and `frames`) and write its row."""
        restored = Restored(self.workdir, self.cfg, self.run_cfg, self.networks, params, update, frames, {})
        row = {"update": update, "frames": frames}
        for houses in self.ec.houses:
            for policy in self.ec.policies:
                result = run_episodes(restored, self.envs[houses], houses, self.ec.episodes, policy=policy,
                                      seed=self.ec.seed, log=self.log, devices=self.devices)
                row.update({f"{houses}/{policy}/{k}": result[k] for k in FIELDS})
        self.writer.write(row)
        return row
