"""Where one training update's time goes (`python -m a2catvn_jax.benchmark profile`).

Each phase of `agent.update` is jitted and timed on its own, on the same state, in one
process, so that the ratios come from one run:

- the rollout (`update.collect`: the policy acts, the environment steps and renders, the
  frames' ground truth is made, the rollout is written to the replay buffer), and the
  environment alone (the same number of steps with random actions);
- the loss, forward and forward + backward: plain A2C's terms (actor, critic, entropy),
  then A2C plus each auxiliary term that the configuration weights, one at a time, whose
  extra time over A2C is that term's cost, then every term together (the update's loss;
  the off-policy critic and pixel control share one replayed unroll, so alone each pays
  for it and together they pay once);
- the optimiser (global-norm clip and RMSprop) on the gradients;
- the whole update, whose time less the sum of the rollout, the whole loss's forward +
  backward and the optimiser is what one program gains or loses over separate ones.

It also counts the floating-point operations of one update's matrix products and
convolutions (`matmul_flops`: from the traced program, loops counted as many times as
they run; XLA's own count takes each loop body once) and reports the rate they reach
against a dense float32 matrix product timed in the same run.

`op_times` lists the XLA operations of the compiled update that take the most time,
from a profiler trace of a few updates: each operation's milliseconds per update (all
its executions, those inside loops included), the program source XLA records for it
(e.g. `transpose(jvp(A2CATNet.vn_heads))/vn/conv_general_dilated`: the backward pass
of the vision heads' convolution) and its output shape.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
import math
import re
import tempfile
import time
from collections import Counter
from pathlib import Path

import jax
import jax.numpy as jnp
import optax

from a2catvn_jax.agent import update as update_lib
from a2catvn_jax.agent.networks import VN_HEADS, make_networks
from a2catvn_jax.bench.throughput import random_steps
from a2catvn_jax.config import Config
from a2catvn_jax.env import NavEnv

AUX_TERMS = ("off_policy_critic", "pixel_control", "reward_prediction", *VN_HEADS)


def _timed(fn, *args, repeats: int) -> float:
    """Seconds per call of jitted `fn(*args)`, after one call that compiles it."""
    jax.block_until_ready(fn(*args))
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = fn(*args)
    jax.block_until_ready(out)
    return (time.perf_counter() - t0) / repeats


def _with_weights(cfg: Config, keep: tuple[str, ...]) -> Config:
    """`cfg` with every auxiliary loss weight not in `keep` set to 0."""
    weights = dataclasses.replace(cfg.train.loss_weights, **{t: 0.0 for t in AUX_TERMS if t not in keep})
    return dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, loss_weights=weights))


def _jaxprs(params: dict):
    """The sub-programs held in an equation's parameters (pjit, custom derivatives, cond, remat)."""
    for value in params.values():
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(v, jax.extend.core.ClosedJaxpr):
                yield v.jaxpr
            elif isinstance(v, jax.extend.core.Jaxpr):
                yield v


def _flops(jaxpr) -> tuple[float, bool]:
    """(FLOPs of the matrix products and convolutions in `jaxpr`, whether a loop of unknown
    length was counted once)."""
    total, unknown = 0.0, False
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += 2 * math.prod(eqn.outvars[0].aval.shape) * math.prod(lhs[i] for i in contract)
        elif name == "conv_general_dilated":
            rhs, spec = eqn.invars[1].aval.shape, eqn.params["dimension_numbers"].rhs_spec
            per_output = rhs[spec[1]] * math.prod(rhs[d] for d in spec[2:])  # input features per group x kernel
            total += 2 * math.prod(eqn.outvars[0].aval.shape) * per_output
        elif name == "scan":
            f, u = _flops(eqn.params["jaxpr"].jaxpr)
            total, unknown = total + eqn.params["length"] * f, unknown or u
        elif name == "cond":
            counts = [_flops(b.jaxpr) for b in eqn.params["branches"]]
            total, unknown = total + max(c[0] for c in counts), unknown or any(c[1] for c in counts)
        else:
            for sub in _jaxprs(eqn.params):
                f, u = _flops(sub)
                total, unknown = total + f, unknown or u or name == "while"
    return total, unknown


def matmul_flops(fn, *args) -> tuple[float, bool]:
    """(FLOPs of the matrix products and convolutions of one call of `fn(*args)`, whether
    some loop of unknown length was counted once, making it a lower bound). A convolution
    counts every multiply-add of its kernel, also those on the zeros of padded borders and of
    a transposed convolution's dilated input (XLA's count leaves the borders out)."""
    return _flops(jax.make_jaxpr(fn)(*args).jaxpr)


def matmul_gflops(size: int = 1024, repeats: int = 20) -> float:
    """GFLOP/s of a dense float32 [size, size] x [size, size] product on the default device."""
    a = jax.random.normal(jax.random.PRNGKey(0), (size, size), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (size, size), jnp.float32)
    seconds = _timed(jax.jit(jnp.matmul), a, b, repeats=repeats)
    return 2 * size**3 / seconds / 1e9


def profile_update(cfg: Config, repeats: int = 5, ops: int = 0) -> dict:
    """Seconds per update of each phase (see the module docstring) of configuration `cfg`,
    and with `ops` > 0 the `ops` most expensive XLA operations of the update (`op_times`)."""
    env = NavEnv(cfg.env)
    networks = make_networks(cfg, env.num_actions)
    fns = update_lib.make_update(env, networks, cfg)
    ts = fns.init(jax.random.PRNGKey(0))
    update = fns.update.lower(ts).compile()  # one compile serves the timing, the trace and its HLO
    ts, _ = update(ts)  # the buffer now holds a rollout
    jax.block_until_ready(ts)
    targets = update_lib.targets_of(update_lib.learner(cfg), env)
    frames = update_lib.frames_per_update(cfg)

    collect = jax.jit(lambda ts: update_lib.collect(update_lib.learner(cfg), env, networks, targets, ts))
    batch = collect(ts)
    phases = {"rollout (environment + policy)": _timed(collect, ts, repeats=repeats)}

    env_steps = random_steps(env, cfg.train.rollout_length)
    phases["  of which the environment alone"] = _timed(env_steps, batch.env_state, jax.random.PRNGKey(1),
                                                        repeats=repeats)

    compiled = {}

    def loss_fns(keep: tuple[str, ...]):
        """(loss, its value and gradient), jitted, with only the auxiliary terms `keep` on;
        one pair per set of terms (with one term on, "+ term" and "every term" are one program)."""
        if keep not in compiled:
            c = _with_weights(cfg, keep)
            loss = lambda params, args: update_lib.loss(update_lib.learner(c), networks, targets, params, *args)[0]  # noqa: E731
            compiled[keep] = jax.jit(loss), jax.jit(jax.value_and_grad(loss))
        return compiled[keep]

    args = batch.loss_args
    w = cfg.train.loss_weights
    on = tuple(t for t in AUX_TERMS if getattr(w, t) > 0)
    a2c_fwd, a2c_fb = loss_fns(())
    phases["loss: A2C (actor, critic, entropy), forward"] = _timed(a2c_fwd, ts.params, args, repeats=repeats)
    a2c = phases["loss: A2C (actor, critic, entropy), forward + backward"] = _timed(a2c_fb, ts.params, args,
                                                                                   repeats=repeats)
    for term in on:
        _, fb = loss_fns((term,))
        phases[f"loss: + {term.replace('_', ' ')}, forward + backward"] = _timed(fb, ts.params, args,
                                                                                 repeats=repeats) - a2c
    all_fwd, all_fb = loss_fns(on)
    whole_loss = a2c
    if on:
        phases["loss: every term, forward"] = _timed(all_fwd, ts.params, args, repeats=repeats)
        whole_loss = phases["loss: every term, forward + backward"] = _timed(all_fb, ts.params, args, repeats=repeats)
    _, grads = all_fb(ts.params, args)
    optimizer = update_lib.make_optimizer(cfg)

    @jax.jit
    def step(grads, opt_state, params):
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    phases["optimiser (clip + RMSprop)"] = _timed(step, grads, ts.opt_state, ts.params, repeats=repeats)

    # the update donates its argument: each call takes the state the one before returned
    jax.block_until_ready(ts)
    t0 = time.perf_counter()
    for _ in range(repeats):
        ts, metrics = update(ts)
    jax.block_until_ready(metrics)
    whole = (time.perf_counter() - t0) / repeats
    parts = phases["rollout (environment + policy)"] + phases["optimiser (clip + RMSprop)"] + whole_loss
    flops, lower_bound = matmul_flops(fns.update, ts)
    top_ops = op_times(update, ts, repeats, ops) if ops > 0 else None
    return {
        "batch": env.num_envs, "resolution": cfg.env.render.image_size, "rollout_length": cfg.train.rollout_length,
        "frames_per_update": frames, "phases_s": phases, "update_s": whole, "sum_of_phases_s": parts,
        "train_fps": frames / whole, "update_matmul_flops": flops, "flops_lower_bound": lower_bound,
        "update_gflops_per_s": flops / whole / 1e9, **({"op_times": top_ops} if top_ops else {}),
    }


_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+) = (\S+)")
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+) .*\{\s*$")
_OP_NAME = re.compile(r'op_name="([^"]*)"')
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_OPCODE = re.compile(r"\s([a-z][\w\-]*)\(")
_CONTROL = ("while", "conditional", "call")  # their time is the time of the operations inside them


def hlo_ops(hlo_text: str) -> dict:
    """Instruction name -> (source, output shape) of a compiled HLO module's text. The
    source is the `op_name` XLA recorded (without the `jit(...)/` prefix); a fusion
    without one takes the first `op_name` inside the computation it calls; an
    instruction left without a source is "OPCODE (no source recorded)", with the opcode
    of the called computation's root for a fusion, else its own (e.g. a copy XLA added)."""
    ops, first_source, root_op, calls, computation = {}, {}, {}, {}, None
    for line in hlo_text.splitlines():
        head = _COMPUTATION.match(line)
        if head and "=" not in line.split("{")[0]:
            computation = head.group(1)
            continue
        m = _INSTRUCTION.match(line)
        if not m:
            continue
        name, shape = m.group(1), m.group(2).split("{")[0].rstrip(",")
        source = _OP_NAME.search(line)
        source = re.sub(r"^jit\([^)]*\)/", "", source.group(1)) if source else ""
        opcode = _OPCODE.search(line[m.end():])
        opcode = opcode.group(1) if opcode else "?"
        if computation is not None:
            if source:
                first_source.setdefault(computation, source)
            if line.lstrip().startswith("ROOT"):
                root_op[computation] = opcode
        called = _CALLS.search(line)
        if called:
            calls[name] = called.group(1)
        ops[name] = (source, shape, opcode)

    def source_of(name, source, opcode):
        called = calls.get(name)
        return (source or first_source.get(called)
                or f"{root_op.get(called, opcode)} (no source recorded)")

    return {name: (source_of(name, source, opcode), shape) for name, (source, shape, opcode) in ops.items()}


def op_times(update, ts, repeats: int = 5, top: int = 15) -> dict:
    """The `top` XLA operations of `update(ts) -> (ts, metrics)` (its argument donated;
    jitted, or already compiled for `ts`) that take the most time over `repeats` calls
    under `jax.profiler.trace`: {"ops": [{op, ms_per_update, calls_per_update, source,
    shape}], "ops_ms_per_update": the time of every operation of the update (loops
    counted by what runs inside them)}."""
    if not isinstance(update, jax.stages.Compiled):
        update = update.lower(ts).compile()
    info = hlo_ops(update.as_text())
    ts, metrics = update(ts)
    jax.block_until_ready(metrics)
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(repeats):
                ts, metrics = update(ts)
            jax.block_until_ready(metrics)
        with gzip.open(next(Path(tmp).rglob("*.trace.json.gz"))) as f:
            events = json.load(f)
    events = events["traceEvents"] if isinstance(events, dict) else events
    micros, calls = Counter(), Counter()
    for e in events:
        name = e.get("name")
        if e.get("ph") == "X" and name in info and not name.startswith(_CONTROL):
            micros[name] += e.get("dur", 0)
            calls[name] += 1
    rows = [{"op": name, "ms_per_update": us / repeats / 1e3, "calls_per_update": calls[name] / repeats,
             "source": info[name][0], "shape": info[name][1]} for name, us in micros.most_common(top)]
    return {"ops": rows, "ops_ms_per_update": sum(micros.values()) / repeats / 1e3}
