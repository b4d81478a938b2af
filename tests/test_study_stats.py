"""The statistics the experiment reports add beside the seed-level t-intervals
(`study.stats`): Wilson's interval of success over pooled episodes, and frames to
threshold as censored data (the Kaplan-Meier restricted mean, the log-rank test) and
success by start distance, each
against SciPy or NumPy computed independently, or against an example worked by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from a2catvn_jax.study import formats, report, stats


@pytest.mark.parametrize("k, n", [(43, 100), (0, 100), (100, 100), (1, 3), (207, 500), (5, 7)])
def test_wilson_interval_matches_scipy(k, n):
    ci = scipy.stats.binomtest(k, n).proportion_ci(0.95, method="wilson")
    assert stats.wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_wilson_interval_by_hand_and_its_edges():
    # 43 of 100, z = 1.959964: centre (0.43 + z^2/200) / (1 + z^2/100) = 0.432658,
    # half z / (1 + z^2/100) * sqrt(0.43 * 0.57 / 100 + z^2 / 40000) = 0.095256.
    low, high = stats.wilson_interval(43, 100)
    assert low == pytest.approx(0.337333, abs=1e-6) and high == pytest.approx(0.527846, abs=1e-6)
    assert stats.wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError, match="successes <= trials"):
        stats.wilson_interval(4, 3)


def test_pooled_success_pools_the_runs_episodes():
    pooled = stats.pooled_success([43, 52, None, 10], [100, 100, None, 50])
    ci = scipy.stats.binomtest(105, 250).proportion_ci(0.95, method="wilson")
    assert pooled["successes"] == 105 and pooled["episodes"] == 250 and pooled["runs"] == 3
    assert pooled["rate"] == pytest.approx(0.42)
    assert (pooled["low"], pooled["high"]) == pytest.approx((ci.low, ci.high))
    assert stats.pooled_success([None], [None]) is None
    assert formats.format_pooled(pooled) == "0.42 [0.36, 0.48]"
    assert formats.format_pooled(pooled, runs=4) == "0.42 [0.36, 0.48] (n=3)"
    assert formats.format_pooled(None) == "–"


def test_episode_successes_from_the_per_episode_list_else_the_rate():
    assert stats.episode_successes({"per_episode": {"success": [True, False, True]}, "success_rate": 0.0,
                                    "episodes": 3}) == 2
    assert stats.episode_successes({"success_rate": 0.4133, "episodes": 75}) == 31


def test_success_by_distance_bands_the_pooled_episodes():
    a = {"per_episode": {"success": [True, False, True, True], "start_distance": [0.5, 1.99, 2.0, 9.5]}}
    b = {"per_episode": {"success": [False, True], "start_distance": [5.0, 7.9]}}
    by = stats.success_by_distance([a, None, b, {"success_rate": 0.5, "episodes": 10}])
    # bands [0, 2), [2, 4), [4, 6), [6, 8), [8, inf): a band's lower edge belongs to it
    assert by == {"edges": [2.0, 4.0, 6.0, 8.0], "successes": [1, 1, 0, 1, 1], "episodes": [2, 1, 1, 1, 1]}
    assert stats.success_by_distance([None, {"success_rate": 0.5, "episodes": 10}]) is None
    summary = {"variants": {"v": {"eval": {"held-out": {"by_distance": by}}}, "w": {"eval": {}}},
               "baselines": {"oracle": {"held-out": b}, "random": {}}}
    assert report.distance_table(summary, "held-out").splitlines() == [
        "| success, held-out houses, by start distance | 0–2 m | 2–4 m | 4–6 m | 6–8 m | 8 m or more |",
        "|---|---|---|---|---|---|",
        "| v | 0.50 (2) | 1.00 (1) | 0.00 (1) | 1.00 (1) | 1.00 (1) |",
        "| shortest-path oracle | – | – | 0.00 (1) | 1.00 (1) | – |"]
    assert report.distance_table(summary, "train") == ""


def test_restricted_mean_by_hand():
    # Runs reach the threshold at 2, 4, 4; two never do and are censored at 3 and 6.
    # Kaplan-Meier: S = 1 on [0, 2); at 2, 5 at risk, 1 reaches: S = 0.8; the censoring at 3
    # leaves 3 at risk at 4, where 2 reach: S = 0.8 / 3 = 0.266667.
    # Up to 5: RMST = 2 * 1 + 2 * 0.8 + 1 * 0.266667 = 3.866667.
    # Variance: A(2) = 1.6 + 0.266667 = 1.866667 and A(4) = 0.266667, the areas from each event
    # time to 5: 1.866667^2 * 1 / (5 * 4) + 0.266667^2 * 2 / (3 * 1) = 0.174222 + 0.047407
    # = 0.221630; se 0.470776; 95%: +- 1.959964 * se = +- 0.922705.
    r = stats.restricted_mean([2.0, 3.0, 4.0, 4.0, 6.0], [True, False, True, True, False], 5.0)
    assert r["mean"] == pytest.approx(3.866667, abs=1e-6)
    assert r["se"] == pytest.approx(0.470776, abs=1e-6)
    assert (r["low"], r["high"]) == pytest.approx((3.866667 - 0.922705, 3.866667 + 0.922705), abs=1e-5)
    assert r["events"] == 3 and r["runs"] == 5 and r["horizon"] == 5.0
    # The same curve integrated numerically from scipy's Kaplan-Meier estimate.
    data = scipy.stats.CensoredData(uncensored=[2.0, 4.0, 4.0], right=[3.0, 6.0])
    grid = np.linspace(0.0, 5.0, 500_001)
    area = np.trapezoid(scipy.stats.ecdf(data).sf.evaluate(grid), grid)
    assert r["mean"] == pytest.approx(area, abs=1e-4)


def test_restricted_mean_without_censoring_is_the_mean():
    # No censoring and a horizon past every time: the area is the sample mean, and
    # Greenwood's variance the plug-in variance of the mean, sum (x - mean)^2 / n^2.
    times = np.array([3.0, 1.0, 4.0, 1.0, 9.0, 2.6])
    r = stats.restricted_mean(times, np.ones(6, bool), 10.0)
    assert r["mean"] == pytest.approx(times.mean())
    assert r["se"] == pytest.approx(times.std() / math.sqrt(times.size))


def test_restricted_mean_of_runs_that_never_reach_and_past_the_horizon():
    none = stats.restricted_mean([5e6] * 5, [False] * 5, 5e6)
    assert (none["mean"], none["low"], none["high"], none["se"], none["events"]) == (5e6, 5e6, 5e6, 0.0, 0)
    assert formats.format_rmst(none) == "5.0M (none reached)"
    # A run that reaches the threshold after the horizon counts as one not reached by then.
    late = stats.restricted_mean([1.0, 2.0, 8.0], [True, True, True], 5.0)
    censored = stats.restricted_mean([1.0, 2.0, 8.0], [True, True, False], 5.0)
    assert late["mean"] == pytest.approx(censored["mean"]) and late["mean"] == pytest.approx(1.0 + 2.0 / 3.0 + 1.0)
    assert late["se"] == pytest.approx(censored["se"]) and late["events"] == 2
    assert formats.format_rmst({**late, "mean": 2.1e6, "low": 1.6e6, "high": 2.6e6}) == "2.1M [1.6M, 2.6M]"
    with pytest.raises(ValueError, match="one time and one reached flag per run"):
        stats.restricted_mean([1.0, 2.0], [True], 3.0)


def test_logrank_by_hand():
    # a: reaches at 1 and 2, one censored at 5; b: two censored at 5.
    # At 1: 3 of a and 2 of b at risk, one event: expected in a 3/5, variance 3/5 * 2/5 = 0.24.
    # At 2: 2 and 2 at risk, one event: expected 1/2, variance 1/4.
    # z = (2 - 1.1) / sqrt(0.49) = 0.9 / 0.7; two-sided p = 2 (1 - Phi(9 / 7)) = 0.198543.
    p = stats.logrank_p([1.0, 2.0, 5.0], [True, True, False], [5.0, 5.0], [False, False])
    assert p == pytest.approx(2 * scipy.stats.norm.sf(9 / 7)) and p == pytest.approx(0.198543, abs=1e-6)
    assert stats.logrank_p([5.0, 5.0], [False, False], [5.0, 5.0], [False, False]) is None  # no event
    assert p == pytest.approx(stats.logrank_p([5.0, 5.0], [False, False], [1.0, 2.0, 5.0], [True, True, False]))


def test_censored_frames():
    times, reached = stats.censored_frames([1e6, None, 2e6], [4e6, 3e6, 5e6])
    assert times.tolist() == [1e6, 3e6, 2e6] and reached.tolist() == [True, False, True]
