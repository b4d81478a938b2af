"""The evaluate command: result fields and their consistency, determinism, the video,
held-out houses, evaluation-only overrides, and clean errors; evaluation during
training (`train.eval`) against it.

One tiny run (16x16 images, 4 environments, 2 updates, evaluated during training at
update 2) is trained per module; every test evaluates or damages (a copy of) it.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np
import pytest

from a2catvn_jax.config import ConfigError, load_config
from a2catvn_jax.env.scenes import mjcf
from a2catvn_jax.env.world import make_scenes
from a2catvn_jax.evaluate import main
from a2catvn_jax.run.evaluation import default_output, evaluate
from a2catvn_jax.run.restore import HELD_OUT_OFFSET, house_env, restore
from a2catvn_jax.run.training import train
from a2catvn_jax.run.video import write_video
from tiny import TINY_LEARNER

EPISODES = 6
TINY = TINY_LEARNER + ["env.scene.num_scenes=1", "env.scene.kind=room", "env.max_episode_steps=20", "train.log_every=1"]
# Evaluation during training at update 2, on the episodes the tests below evaluate.
DURING = ["train.eval.every=2", f"train.eval.episodes={EPISODES}", "train.eval.seed=3",
          "train.eval.houses=[train, held-out]", "train.eval.policies=[sample, greedy]"]
FIELDS = ("step", "frames", "episodes", "success_rate", "spl", "episode_length", "episode_return", "houses", "policy",
          "per_episode")
PER_EPISODE = ("success", "length", "spl", "return", "start_distance")


def quiet(*_):
    pass


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("run")
    train(load_config(None, TINY + DURING), workdir, max_updates=2, progress=False, log=quiet)
    return workdir


@pytest.fixture(scope="module")
def cli_result(run, tmp_path_factory):
    """The CLI's JSON and GIF for EPISODES episodes of seed 3."""
    video = tmp_path_factory.mktemp("video") / "agent.gif"
    main(["--workdir", str(run), "--episodes", str(EPISODES), "--seed", "3", "--video", str(video),
          "--video-episodes", "1"])
    return json.loads(default_output(run, {"step": 2, "houses": "train", "policy": "sample"}).read_text()), video


def test_result_fields_are_consistent(cli_result):
    result, _ = cli_result
    for key in FIELDS:
        assert key in result
    assert result["step"] == 2 and result["frames"] == 2 * 4 * 4
    assert result["houses"] == "train" and result["policy"] == "sample"
    assert result["episodes"] == EPISODES
    per = result["per_episode"]
    assert all(len(per[k]) == EPISODES for k in PER_EPISODE)
    assert 0.0 <= result["spl"] <= result["success_rate"] <= 1.0
    assert result["success_rate"] == pytest.approx(np.mean(per["success"]))
    assert result["episode_length"] == pytest.approx(np.mean(per["length"]))
    assert result["episode_return"] == pytest.approx(np.mean(per["return"]))
    assert all(1 <= n <= 20 for n in per["length"])
    assert all(0.0 <= spl <= s for spl, s in zip(per["spl"], per["success"]))
    assert per["return"] == [float(s) for s in per["success"]]  # reward 1 on success only
    assert all(d > 0 for d in per["start_distance"])
    assert result["eval_frames"] % 4 == 0 and result["eval_frames"] >= sum(per["length"])


def test_same_seed_same_result(run, cli_result):
    expected, _ = cli_result
    again = evaluate(run, EPISODES, seed=3, log=quiet)
    assert again == {k: v for k, v in expected.items() if k != "video"}


def test_evaluation_during_training_is_evaluate_at_that_update(run, cli_result):
    """The row that `train.eval` wrote at update 2 holds, for each house set and policy,
    what `evaluate` measures from the checkpoint of update 2 with the same episodes."""
    rows = [json.loads(line) for line in (run / "eval.jsonl").read_text().splitlines()]
    assert [(r["update"], r["frames"]) for r in rows] == [(2, 2 * 4 * 4)]
    row = rows[0]
    assert set(row) == {"update", "frames"} | {f"{h}/{p}/{k}" for h in ("train", "held-out") for p in ("sample", "greedy")
                                               for k in ("success_rate", "spl", "episode_length")}
    expected, _ = cli_result  # training houses, sampled, seed 3
    greedy = evaluate(run, EPISODES, seed=3, houses="held-out", policy="greedy", log=quiet)
    for houses, policy, result in (("train", "sample", expected), ("held-out", "greedy", greedy)):
        for k in ("success_rate", "spl", "episode_length"):
            assert row[f"{houses}/{policy}/{k}"] == pytest.approx(result[k], abs=1e-9), (houses, policy, k)
    assert all(0 <= row[f"{h}/{p}/spl"] <= row[f"{h}/{p}/success_rate"] <= 1 and
               1 <= row[f"{h}/{p}/episode_length"] <= 20 for h in ("train", "held-out") for p in ("sample", "greedy"))
    header = (run / "eval.csv").read_text().splitlines()[0].split(",")
    assert header == list(row)


def test_evaluation_during_training_needs_a_single_process(tmp_path, monkeypatch):
    """A run of several processes refuses `train.eval` in one line, before it builds
    anything (its checkpoints are evaluated afterwards instead)."""
    import jax

    from a2catvn_jax.run.training import TrainingError

    monkeypatch.setattr(jax, "process_count", lambda: 2)
    with pytest.raises(TrainingError, match="^train.eval.every: evaluation during training runs in a single process"):
        train(load_config(None, TINY + DURING), tmp_path / "w", max_updates=1, progress=False, log=quiet)
    assert not (tmp_path / "w" / "checkpoints").exists()


def test_video_has_three_panels(cli_result):
    _, video = cli_result
    frames = iio.imread(video, index=None)
    assert frames.ndim == 4 and len(frames) >= 2
    assert frames.shape[1:3] == (128, 3 * 128)  # 16 px images upscaled 8x: observation | target | map


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg runs ffmpeg in a subprocess
def test_mp4_video_holds_the_same_frames(cli_result, tmp_path):
    _, gif = cli_result
    frames = iio.imread(gif, index=None)[..., :3]
    mp4 = tmp_path / "agent.mp4"
    write_video(mp4, list(frames))
    with imageio.get_reader(mp4) as reader:
        back = np.stack([frame for frame in reader.iter_data()])
    assert back.shape == frames.shape
    # lossy H.264: close to the source on average, and the frames still differ from each other as they did
    assert np.abs(back.astype(float) - frames).mean() < 8.0
    assert np.abs(back[-1].astype(float) - back[0]).mean() > 0.5 * np.abs(frames[-1].astype(float) - frames[0]).mean()


def test_held_out_houses(run, cli_result):
    cfg = load_config(None, TINY)
    train_scene, held_scene = make_scenes(cfg.env)[0], make_scenes(cfg.env, HELD_OUT_OFFSET)[0]
    layout = mjcf.layout_of([train_scene, held_scene])
    assert mjcf.scene_to_mjcf(train_scene, layout) != mjcf.scene_to_mjcf(held_scene, layout)

    result = evaluate(run, 3, houses="held-out", policy="greedy", overrides=["env.num_envs=2", "env.max_episode_steps=8"],
                      log=quiet)
    assert result["houses"] == "held-out" and result["policy"] == "greedy" and result["num_envs"] == 2
    assert result["scenes"] == [held_scene.name] and result["scenes"] != cli_result[0]["scenes"]
    assert result["episodes"] == 3 and all(n <= 8 for n in result["per_episode"]["length"])


def test_new_targets_keep_the_houses_and_change_the_goals(run, cli_result):
    cfg = load_config(None, TINY)
    train_env, new_env = house_env(cfg.env, "train"), house_env(cfg.env, "new-targets")
    assert [s.name for s in new_env.world.scenes] == [s.name for s in train_env.world.scenes]
    assert not np.allclose(np.asarray(new_env.world.arrays.target_pose), np.asarray(train_env.world.arrays.target_pose))

    result = evaluate(run, 2, houses="new-targets", overrides=["env.num_envs=2", "env.max_episode_steps=8"], log=quiet)
    assert result["houses"] == "new-targets" and result["scenes"] == cli_result[0]["scenes"]
    assert result["episodes"] == 2


def test_network_changes_are_refused(run, capsys):
    with pytest.raises(ConfigError, match="agent.core_size"):
        evaluate(run, 1, overrides=["agent.core_size=32"], log=quiet)
    # What the trained network is shown may change: `agent.blind` zeroes its inputs.
    for mode in ("target", "observation", "both"):
        restored = restore(run, overrides=[f"agent.blind={mode}"])
        assert restored.networks.blind == mode and restored.run_cfg.agent.blind == "none"
    with pytest.raises(SystemExit) as exc:
        main(["--workdir", str(run), "--set", "env.render.image_size=32"])
    assert exc.value.code == 2 and "env.render.image_size" in capsys.readouterr().err


def _error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2, err
    assert "Traceback" not in err
    return err.splitlines()[-1]


def test_clean_errors(run, tmp_path, capsys):
    assert _error(["--workdir", str(run), "--episodes", "0"], capsys).endswith("--episodes must be >= 1, got 0")
    assert _error(["--workdir", str(run), "--step", "7"], capsys) == (
        f"error: {run.absolute()}: no checkpoint at update 7; available: [0, 2]"
    )
    assert _error(["--workdir", str(tmp_path / "missing")], capsys) == f"error: {tmp_path / 'missing'}: no such directory"


def _cli(workdir) -> tuple[int, list[str]]:
    proc = subprocess.run([sys.executable, "-m", "a2catvn_jax.evaluate", "--workdir", str(workdir)],
                          capture_output=True, text=True, timeout=120)
    return proc.returncode, proc.stderr.strip().splitlines()


def test_cli_without_checkpoints(run, tmp_path):
    shutil.copy(run / "config.yaml", tmp_path / "config.yaml")
    assert _cli(tmp_path) == (2, [f"error: {tmp_path}: no checkpoints (missing checkpoints/)"])


def test_cli_corrupt_checkpoint(run, tmp_path):
    shutil.copytree(run, tmp_path, dirs_exist_ok=True)
    arrays = [p for p in (tmp_path / "checkpoints" / "2" / "state").rglob("d/*") if p.is_file()]
    assert arrays
    for path in arrays:
        path.write_bytes(b"not an array")
    rc, err = _cli(tmp_path)
    assert rc == 2 and len(err) == 1
    assert err[0].startswith(f"error: {tmp_path / 'checkpoints' / '2'}: the checkpoint is corrupt")


def test_random_policy_baseline(run):
    """`policy="random"` runs the same evaluation with uniformly random actions."""
    kwargs = dict(overrides=["env.max_episode_steps=40", "env.success_heading_deg=180"], log=quiet)
    random_result = evaluate(run, 8, policy="random", **kwargs)
    sampled = evaluate(run, 8, policy="sample", **kwargs)
    assert random_result["policy"] == "random" and random_result["episodes"] == 8
    assert 0 <= random_result["spl"] <= random_result["success_rate"] <= 1
    per_r, per_s = random_result["per_episode"], sampled["per_episode"]
    assert (per_r["length"], per_r["spl"]) != (per_s["length"], per_s["spl"])


def test_baselines_need_no_run(run, tmp_path, capsys, monkeypatch):
    """`--config FILE --policy random|oracle` evaluates a baseline without a run: the random
    policy's episodes are those it plays beside a run of the same configuration, and the
    shortest-path oracle succeeds in every episode."""
    cfg_file = run / "config.yaml"
    random_run = evaluate(run, EPISODES, policy="random", seed=1, log=quiet)
    monkeypatch.chdir(tmp_path)
    main(["--config", str(cfg_file), "--policy", "random", "--episodes", str(EPISODES), "--seed", "1"])
    random_alone = json.loads((tmp_path / "baseline_train_random.json").read_text())
    assert random_alone["per_episode"] == random_run["per_episode"]
    assert random_alone["workdir"] is None and random_alone["frames"] == 0
    main(["--config", str(cfg_file), "--policy", "oracle", "--episodes", str(EPISODES), "--out", "oracle.json"])
    oracle = json.loads((tmp_path / "oracle.json").read_text())
    assert oracle["policy"] == "oracle" and oracle["success_rate"] == 1.0
    assert 0 < oracle["spl"] <= 1
    assert _error(["--config", str(cfg_file), "--policy", "sample"], capsys).endswith(
        "without a run, --policy must be a baseline: random, oracle, tour")
    assert _error(["--config", str(cfg_file), "--workdir", str(run)], capsys).endswith(
        "give --workdir DIR (a trained run) or --config FILE (a baseline without a run)")


def test_evaluation_with_its_baselines(run):
    """`baselines=True` adds the random policy's and the oracle's numbers, the same as
    evaluating each policy on its own."""
    result = evaluate(run, EPISODES, seed=1, baselines=True, log=quiet)
    assert set(result["baselines"]) == {"random", "oracle"}
    for policy, numbers in result["baselines"].items():
        alone = evaluate(run, EPISODES, seed=1, policy=policy, log=quiet)
        assert numbers == {k: alone[k] for k in ("success_rate", "spl", "episode_length")}
    assert result["baselines"]["oracle"]["success_rate"] == 1.0
