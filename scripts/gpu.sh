#!/usr/bin/env bash
# The GPU measurements of docs/benchmarks.md in one script, each step under its own time
# limit (120 + 120 + 60 + 90 + 150 s) so that the whole stays under 10 minutes:
#   1. the environment (move + render, RGB + depth + segmentation) with both render
#      backends side by side, B 256 .. 8192, at 64 and 84 px;
#   2. training frames/s and memory of the paper-sized configuration at 32 px,
#      B 256 .. 4096 (one process per size);
#   3. the profile of one update at B 1024;
#   4. the update loop at B 1024 with the large-batch recipe (configs/presets/large_batch.yaml:
#      5-step rollouts, clip 40, and here one gradient step per 64 environments,
#      train.minibatches = B / 64): one update per call against 10 per call in the device loop;
#   5. a training run of the command line on every device of the machine at B 4096 with
#      the same recipe (image_goals_cpu, 30 updates): its log (frames/s, compile,
#      memory) and metrics.
# Results go to OUT (default: gpu_results/) as JSON and text, with the device's name.
#
#   scripts/gpu.sh [OUT]
#   SMALL=1 scripts/gpu.sh /tmp/gpu   # the same steps at tiny sizes (checks the script on a CPU)
set -u
out=${1:-gpu_results}
mkdir -p "$out"
python=${PYTHON:-python3}
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # the benchmark's processes share the device's memory
if [ "${SMALL:-0}" = 1 ]; then
  env_sizes="2 4" env_res="16" train_sizes="2 4" profile_b=2 run_b=4 steps=1 limits=(600 600 600 600 600)
  tiny=(--set env.scene.kind=room env.render.culling=false agent.conv_channels=[4,8,8,8] agent.dense_size=16
        agent.core_size=16 train.rollout_length=4 train.replay_size=8 train.replay_batch=2)
else
  env_sizes="256 1024 4096 8192" env_res="64 84" train_sizes="256 1024 4096" profile_b=1024 run_b=4096 steps=5
  limits=(120 120 60 90 150)
  tiny=()
fi
"$python" -c "import jax; print(jax.devices())" | tee "$out/device.txt"
steps_of() {  # the large-batch recipe's gradient steps per rollout at B environments: one per 64
  echo $(( $1 >= 64 ? $1 / 64 : 1 ))
}
step() {  # step NAME SECONDS COMMAND...: run one step, its output in OUT/NAME.txt
  local name=$1 seconds=$2
  shift 2
  echo "== $name (at most ${seconds} s)"
  timeout "$seconds" "$@" 2>&1 | grep -v "^Module " | tee "$out/$name.txt"
  echo "== $name: exit status ${PIPESTATUS[0]}"
}
step env "${limits[0]}" "$python" -m a2catvn_jax.benchmark env --batch-sizes $env_sizes --resolutions $env_res \
  --steps "$steps" --no-gl --max-pixels 1e9 --json "$out/env.json" "${tiny[@]}"
step train "${limits[1]}" "$python" -m a2catvn_jax.benchmark train --configs paper --paper-resolution 32 \
  --batch-sizes $train_sizes --updates "$steps" --json "$out/train.json" "${tiny[@]}"
step profile "${limits[2]}" "$python" -m a2catvn_jax.benchmark profile --configs paper --paper-resolution 32 \
  --updates 2 --json "$out/profile.json" --set env.num_envs=$profile_b "${tiny[@]:1}"
step loop "${limits[3]}" "$python" -m a2catvn_jax.benchmark loop --configs paper --paper-resolution 32 \
  --updates 10 --per-call 10 --repeats 2 --json "$out/loop.json" \
  --set env.num_envs=$profile_b train.rollout_length=5 train.max_grad_norm=40 \
  train.minibatches=$(steps_of $profile_b) "${tiny[@]:1}"
step run "${limits[4]}" "$python" -m a2catvn_jax.train --config configs/image_goals_cpu.yaml \
  configs/presets/large_batch.yaml --workdir "$out/run" --updates 30 --no-progress \
  --set env.num_envs=$run_b train.minibatches=$(steps_of $run_b) train.log_every=5 train.checkpoint_every=30 \
  "${tiny[@]:1}"
