"""Evaluate a trained agent: success rate, SPL, episode statistics, and a video.

    python -m a2catvn_jax.evaluate --workdir DIR [--episodes 100] [--step N]
        [--houses train|held-out|new-targets] [--policy sample|greedy|random|oracle|tour] [--video FILE.gif|.mp4]
        [--video-episodes 2] [--out FILE.json] [--seed 0] [--baselines] [--devices N] [--set KEY=VALUE ...]
    python -m a2catvn_jax.evaluate --config FILE --policy random|oracle|tour [--episodes 100] [...]

The parameters of a checkpoint of the run in DIR (the latest, or update N) are
restored with the run's own configuration. Evaluation only reads the run: it takes no
lock and may run while the run trains (orbax's checkpoints appear when complete); when
a checkpoint cannot be read, the error names those that can (`--step N`). The policy (sampled; its argmax with
`--policy greedy`; or a baseline: uniformly random actions with `--policy random`, the
shortest-path oracle with `--policy oracle`, on room-type goals the tour with
`--policy tour`, which knows the map but not the goal and looks into the nearest room
it has not yet seen until the episode ends: `env.tour`) then acts in all B environments at
curriculum complexity 1 until every environment has finished ceil(episodes / B)
episodes; the first `--episodes` of these, in environment order, are counted, so that
short episodes are not favoured. Without a run (`--config FILE` instead of `--workdir`)
the baselines run in the houses of that configuration.

`--houses held-out` generates houses the run never trained in (the same generator and
settings, seeds offset by `HELD_OUT_OFFSET`); `--houses new-targets` keeps the training
houses but draws their goals anew (other target poses and images, goal seed offset by
`NEW_TARGETS_OFFSET`). `--set` changes evaluation settings
(`env.num_envs`, `env.max_episode_steps`, `env.complexity`, noise, ...); keys that
shape the network are refused.

The result is printed and written as JSON (default DIR/eval_<step>_<houses>_<policy>.json;
for a baseline without a run, baseline_<houses>_<policy>.json in the current directory).
`--video` shows agent 0's first episodes: observation | target image | top-down map
with the path so far, the agent's pose (blue) and the target pose (red).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from a2catvn_jax import cli
from a2catvn_jax.errors import UserError
from a2catvn_jax.run.evaluation import BASELINES, POLICIES, default_output, evaluate, evaluate_baseline, to_json
from a2catvn_jax.run.restore import HOUSES
from a2catvn_jax.run.video import FORMATS


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m a2catvn_jax.evaluate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", default=None, help="the training run's work directory")
    parser.add_argument("--episodes", type=int, default=100, help="episodes to count (default 100)")
    parser.add_argument("--step", type=int, default=None, help="checkpoint update to evaluate (default: the latest)")
    parser.add_argument("--houses", choices=HOUSES, default="train", help="the training houses, held-out ones, or the training houses with new targets")
    parser.add_argument("--policy", choices=POLICIES, default="sample",
                        help="sample from the policy, take its argmax, or a baseline: uniformly random actions, "
                             "the shortest-path oracle or the goal-blind tour of the rooms (room-type goals)")
    parser.add_argument("--video", default=None, metavar="FILE",
                        help="video of agent 0 (.gif, or .mp4 with imageio-ffmpeg)")
    parser.add_argument("--video-episodes", type=int, default=2, help="episodes in the video (default 2)")
    parser.add_argument("--out", default=None, metavar="FILE",
                        help="result JSON (default DIR/eval_<step>_<houses>_<policy>.json)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--baselines", action="store_true",
                        help="also run the baselines (random policy, shortest-path oracle; on room-type goals the "
                             "tour) in the same houses")
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="split the environments over the first N local devices (default: all of them)")
    cli.add_config_args(parser, help="evaluation settings, e.g. --set env.num_envs=32 env.max_episode_steps=500")
    args = parser.parse_args(argv)
    if (args.workdir is None) == (args.config is None):
        parser.error("give --workdir DIR (a trained run) or --config FILE (a baseline without a run)")
    if args.workdir is None and args.policy not in BASELINES:
        parser.error(f"without a run, --policy must be a baseline: {', '.join(BASELINES)}")
    if args.workdir is None and args.step is not None:
        parser.error("--step needs --workdir")
    if args.devices is not None and args.devices < 1:
        parser.error(f"--devices must be >= 1, got {args.devices}")
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.video_episodes < 1:
        parser.error(f"--video-episodes must be >= 1, got {args.video_episodes}")
    if args.video is not None and Path(args.video).suffix.lower() not in FORMATS:
        parser.error(f"--video must end in .gif or .mp4, got {args.video!r}")

    with cli.errors(parser, code=2, kinds=(UserError, ValueError)):
        if args.workdir is None:
            result = evaluate_baseline(cli.config_from_args(args), args.episodes, houses=args.houses,
                                       policy=args.policy, seed=args.seed, video=args.video,
                                       video_episodes=args.video_episodes, devices=args.devices)
        else:
            result = evaluate(args.workdir, args.episodes, step=args.step, houses=args.houses, policy=args.policy,
                              seed=args.seed, overrides=cli.overrides_of(args), video=args.video,
                              video_episodes=args.video_episodes, baselines=args.baselines, devices=args.devices)
    if args.out:
        out = Path(args.out)
    elif args.workdir is None:
        out = Path(f"baseline_{result['houses']}_{result['policy']}.json")
    else:
        out = default_output(args.workdir, result)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(to_json(result))
    except OSError as e:  # a full disk included
        parser.exit(1, f"error: cannot write the result to {out}: {e.strerror or e}\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
