import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

# One compilation cache for the whole session, the pytest-xdist workers and subprocesses
# (the command-line tests) included: tests that build the same tiny configuration compile
# its programs once. Set before anything imports JAX; a fresh directory, so no test sees an
# older session's. The first process to load this file (the xdist controller, or pytest
# alone) makes it and removes it at exit; the workers it starts inherit the variable.
_CACHE = os.environ.get("A2CATVN_TEST_JAX_CACHE")
if _CACHE is None or not os.path.isdir(_CACHE):
    _CACHE = tempfile.mkdtemp(prefix="a2catvn-jax-cache-")
    os.environ["A2CATVN_TEST_JAX_CACHE"] = _CACHE
    atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["JAX_COMPILATION_CACHE_DIR"] = _CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"

# Compile time is most of the suite's time, and the tests' programs are tiny: XLA's CPU
# backend compiles them without LLVM's optimisation passes (about 40% less compile time,
# the programs about 2x slower) and emits its fused loops the older way instead of through
# its fusion emitters (the tiny learner's update: compile 5.4 s instead of 12 s, runs 64-70
# ms instead of 51-61). The functions computed stay the same; the older emitter may round
# some results differently (test_render.py::test_culling_changes_nothing). Benchmarks and
# training outside the tests keep the defaults. An XLA that does not know a flag aborts
# the process, so each flag is first tried in a subprocess, once per session (the workers
# and the tests' subprocesses inherit the result).
_FAST_COMPILE = ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false")


def _xla_knows(flag: str) -> bool:
    env = dict(os.environ, XLA_FLAGS=flag, JAX_PLATFORMS="cpu")
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env, capture_output=True, timeout=300)
    return probe.returncode == 0


if "A2CATVN_TEST_XLA_FLAGS" not in os.environ:
    os.environ["A2CATVN_TEST_XLA_FLAGS"] = " ".join(f for f in _FAST_COMPILE if _xla_knows(f))
for _flag in os.environ["A2CATVN_TEST_XLA_FLAGS"].split():
    if _flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_flag}".strip()


# pytest-xdist (`--dist loadfile`) hands whole files to its workers in collection order.
# The longest files go first (measured with `--durations`), so that the workers' last
# files are short ones and the two finish close together; within a file the order stays.
_LONGEST_FIRST = ("test_learner_math.py", "test_env.py", "test_learning.py", "test_notebooks.py", "test_train.py",
                  "test_evaluate.py", "test_networks.py", "test_backends.py", "test_experiments.py", "test_profile.py",
                  "test_success.py", "test_env_contract.py", "test_replay_warmup.py", "test_pretrain.py",
                  "test_render.py", "test_sharding.py", "test_checkpoint_format.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(Path(str(item.fspath)).name, len(rank)))
