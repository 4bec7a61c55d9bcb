"""The statistics every claim is judged by, and the one table formatter: mean ± standard error over
seeds, the paired t-test of two rows (scipy.stats), the verdict, markdown cells and tables."""

from __future__ import annotations

import math
import statistics
from typing import NamedTuple

import scipy.stats

NOTHING_TO_TRAIN = ("No prediction", "GT prediction")  # one run, the same every seed: s.e. 0
P_REPRODUCED = 0.05  # a claim is reproduced only below this two-sided p, in the paper's direction


def mean_se(xs):
    """Mean and standard error; the s.e. of one number is unknown (nan)."""
    xs = list(xs)
    return statistics.fmean(xs), (float(scipy.stats.sem(xs)) if len(xs) > 1 else math.nan)


def plus_minus(fmt: str, mean: float, se: float) -> str:
    """'mean ± s.e.' in fmt; 'mean ± n/a (1 seed)' where the s.e. is nan."""
    return f"{fmt.format(mean)} ± " + ("n/a (1 seed)" if math.isnan(se) else fmt.format(se))


class PairedDifference(NamedTuple):
    """method - baseline over seeds: mean, s.e., t, the paired t-test's two-sided p, and in how
    many of the n seeds the method is lower (better, for a cost) or higher (worse)."""

    mean: float
    se: float
    t: float
    p: float
    better: int
    worse: int
    n: int


def paired_difference(baseline: list, method: list) -> PairedDifference:
    """method[i] - baseline[i] for seed i: pairing removes what a seed's two runs share (data,
    evaluation set). One seed: s.e., t and p nan; no spread: s.e. 0, t = ±inf, p = 0 (or nan)."""
    if len(baseline) != len(method):
        raise ValueError(
            f"method: {len(method)} seeds, but baseline has {len(baseline)}; seeds pair by index"
        )
    if not baseline:
        raise ValueError("baseline: no seeds to compare")
    d = [b - a for a, b in zip(baseline, method)]
    m, se = mean_se(d)
    if se > 0:
        test = scipy.stats.ttest_rel(method, baseline)  # two-sided
        t, p = float(test.statistic), float(test.pvalue)
    else:
        t, p = (math.copysign(math.inf, m), 0.0) if m != 0 and se == 0 else (math.nan, math.nan)
    return PairedDifference(m, se, t, p, sum(x < 0 for x in d), sum(x > 0 for x in d), len(d))


def claim_verdict(p: PairedDifference, direction: int = -1) -> str:
    """'reproduced' only when p < P_REPRODUCED in the paper's direction (-1: the method lower, +1:
    higher); 'contradicted' when so the other way."""
    if p.n == 0:
        return "untested (no seed trained both rows)"
    if not p.se >= 0:  # nan: one seed
        return "untested (one seed: no standard error)"
    if p.p < P_REPRODUCED:
        return "reproduced" if p.mean * direction > 0 else "contradicted (the other way)"
    return "not reproduced"


def p_value(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}" if p < 0.1 else f"p = {p:.2f}"


def cell(values, fmt="{:.2f}", row: str = "") -> str:
    """'mean ± s.e.' of a cell's per-seed values; '--' for none; s.e. 0 for NOTHING_TO_TRAIN."""
    if not values:
        return "--"
    mean, se = mean_se(values)
    return plus_minus(fmt, mean, 0.0 if row in NOTHING_TO_TRAIN else se)


def markdown_table(head, rows) -> str:
    """A markdown table: head [str], rows [[str]]."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])
