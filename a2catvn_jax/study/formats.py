"""How the reports and comparisons write their numbers: frame counts, estimates with
their intervals, frames to a threshold, restricted means, pooled rates, seed lists."""

from __future__ import annotations

from typing import Callable, Optional, Sequence

from a2catvn_jax.study.stats import estimate


def frames_text(value: float) -> str:
    """0, 400k, 1.2M."""
    if value == 0:
        return "0"
    return f"{value / 1e6:.1f}M" if value >= 1e6 else f"{value / 1e3:.0f}k"


def format_frames(per_run: Sequence[Optional[float]], f_max: float) -> str:
    """Frames to threshold over runs: the mean and interval of the runs that reach it,
    and how many never do (e.g. `410k [350k, 470k], 4/5 reached; 1 not by 2.0M`)."""
    reached = [v for v in per_run if v is not None]
    n, k = len(per_run), len(reached)
    if k == 0:
        return f"0/{n} reached by {frames_text(f_max)}"
    text = f"{estimate(reached, 0.0, f_max).format(frames_text)}, {k}/{n} reached"
    return text if k == n else f"{text}; {n - k} not by {frames_text(f_max)}"


def format_rmst(rmst: Optional[dict]) -> str:
    """A restricted mean time to threshold: `2.1M [1.6M, 2.6M]`; the horizon itself when no
    run reaches the threshold before it."""
    if rmst is None:
        return "–"
    if rmst["events"] == 0:
        return f"{frames_text(rmst['horizon'])} (none reached)"
    return f"{frames_text(rmst['mean'])} [{frames_text(rmst['low'])}, {frames_text(rmst['high'])}]"


def format_pooled(pooled: Optional[dict], runs: Optional[int] = None) -> str:
    """Success over pooled episodes with Wilson's interval: `0.41 [0.38, 0.44]`; `(n=k)`
    when only k of `runs` runs have it; – without any."""
    if pooled is None:
        return "–"
    text = f"{pooled['rate']:.2f} [{pooled['low']:.2f}, {pooled['high']:.2f}]"
    return text if runs is None or pooled["runs"] == runs else f"{text} (n={pooled['runs']})"


def format_estimate(values, lo: float = 0.0, hi: float = 1.0, fmt: Callable[[float], str] = "{:.2f}".format) -> str:
    """`0.62 [0.55, 0.69]` over the values present; `(n=k)` when some are missing; – when none is."""
    est = estimate(values, lo, hi)
    if est is None:
        return "–"
    return est.format(fmt) + ("" if est.n == len(values) else f" (n={est.n})")


def seeds_text(seeds: Sequence[int]) -> str:
    seeds = sorted(seeds)
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}–{seeds[-1]}"
    return ", ".join(map(str, seeds))
