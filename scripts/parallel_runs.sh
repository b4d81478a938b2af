#!/usr/bin/env bash
# Train an experiment's runs side by side on one machine with a GPU (or many cores): one
# process per (variant, seed), at most JOBS at a time, each stopped at DEADLINE seconds after
# the start. Each run that finishes is stored by the runner under STORE, exactly as
# `python -m a2catvn_jax.experiments NAME --seeds S --train-only LABEL` stores it; a run cut
# off by the deadline leaves nothing there. The log of every process is in LOGS.
#
#   scripts/parallel_runs.sh NAME STORE LOGS JOBS DEADLINE SEED:LABEL [SEED:LABEL ...]
#   scripts/parallel_runs.sh sight /tmp/store /tmp/logs 4 480 2:A2CAT-VN "2:blind A2CAT-VN"
#
# On one GPU use JOBS=1: one quickstart run alone trains at about 25k frames/s on an H200,
# while six at once took 3 minutes to compile and then shared the GPU so badly that none
# finished 1.5M frames in 4.5 minutes (docs/benchmarks.md). With JOBS > 1 on a GPU, set
# XLA_PYTHON_CLIENT_PREALLOCATE=false so that the processes share its memory.
# RUNNER_ARGS is added to every runner's command line (e.g. "--episodes 20").
set -u
name=$1 store=$2 logs=$3 jobs=$4 deadline=$5
shift 5
mkdir -p "$store" "$logs"
python=${PYTHON:-python3}
# Runs of one configuration compile the same programs: keep them in a persistent cache.
export JAX_COMPILATION_CACHE_DIR=${JAX_COMPILATION_CACHE_DIR:-${ROOT:-runs/experiments}/.jax_cache}
start=$(date +%s)
for job in "$@"; do
  seed=${job%%:*} label=${job#*:}
  while [ "$(jobs -rp | wc -l)" -ge "$jobs" ]; do wait -n; done
  left=$(( deadline - ($(date +%s) - start) ))
  if [ "$left" -le 0 ]; then echo "deadline: $job not started"; continue; fi
  tag="${name}_seed${seed}_$(echo -n "$label" | tr -c 'A-Za-z0-9' '_')"
  log="$logs/$tag.log"
  echo "start $job ($left s left) -> $log"
  timeout --signal=KILL "$left" "$python" -m a2catvn_jax.experiments "$name" --seeds "$seed" --train-only "$label" \
    --store "$store" --docs "$logs/docs_$tag" --root "${ROOT:-runs/experiments}" ${RUNNER_ARGS:-} >"$log" 2>&1 &
done
wait
echo "all done after $(( $(date +%s) - start )) s"
