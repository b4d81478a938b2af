import atexit
import json
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
# The longest files go first, so that the workers' last files are short ones and the two
# finish close together; within a file the order stays. The order comes from the seconds
# each file took when last measured (tests/durations.json, written by
# `pytest --record-durations`); a file not measured yet counts as the longest.
_DURATIONS = Path(__file__).with_name("durations.json")


def pytest_addoption(parser):
    parser.addoption("--record-durations", action="store_true",
                     help=f"write each test file's seconds (setup, call, teardown) to {_DURATIONS.name}")


def _durations() -> dict:
    try:
        return json.loads(_DURATIONS.read_text())
    except (OSError, ValueError):
        return {}


def pytest_collection_modifyitems(session, config, items):
    seconds = _durations()
    longest = max(seconds.values(), default=0.0) + 1.0
    items.sort(key=lambda item: -seconds.get(Path(str(item.fspath)).name, longest))


_MEASURED: dict = {}


def pytest_runtest_logreport(report):
    name = Path(report.nodeid.split("::")[0]).name
    _MEASURED[name] = _MEASURED.get(name, 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    if session.config.getoption("--record-durations") and _MEASURED and not hasattr(session.config, "workerinput"):
        merged = {**_durations(), **{k: round(v, 1) for k, v in _MEASURED.items()}}
        _DURATIONS.write_text(json.dumps(dict(sorted(merged.items(), key=lambda kv: -kv[1])), indent=1) + "\n")
