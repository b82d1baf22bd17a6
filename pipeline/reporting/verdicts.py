"""The report's verdicts: for each pair of comparable methods that was run, whether the first
beat, lost to or tied with the second on re-evaluated hypervolume, paired over seeds, with the
rule (beyond the seed noise, or a minimum difference with one seed) and the numbers stated."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.evaluation.metrics import mean_sem
from pipeline.reporting.presentation import HYBRID_METHODS, VARIANT_BASES, VARIANT_METHODS, label
from pipeline.reporting.runs import Run
from pipeline.reporting.tables import fmt_num

# How VERDICT_PAIRS names MAPEX against its warm-up-only ablation (the paper's form only: see hv_verdict)
ABLATION = "the advantage-weighted phase"
# Comparisons the verdict section states when both methods of a pair were run: (a, b, what a is).
VERDICT_PAIRS = (
    ("mapex_pderl", "warmup_only_pderl", f"{ABLATION} (MAPEX)"),
    ("mapex_td3", "warmup_only_td3", f"{ABLATION} (MAPEX-TD3)"),
    ("mapex_posthoc_imported", "warmup_only_imported", f"{ABLATION} (MAPEX-PostHoc, imported)"),
    # weight-space interpolation between the same specialists (a baseline the paper does not have)
    ("mapex_pderl", "interpolate_pderl", "MAPEX"),
    ("mapex_td3", "interpolate_td3", "MAPEX-TD3"),
    ("mapex_posthoc_imported", "interpolate_imported", "MAPEX-PostHoc (imported)"),
    ("mapex_posthoc_pderl", "mapex_pderl", "MAPEX-PostHoc (post-hoc critics)"),
    ("mapex_posthoc_td3", "mapex_td3", "MAPEX-TD3-PostHoc (post-hoc critics)"),
    ("mapex_pderl", "mapex_td3", "MAPEX (PDERL specialists)"),
    ("mapex_pderl", "mopderl", "MAPEX"),
    ("mapex_pderl", "morld", "MAPEX"),
)


@dataclass(frozen=True)
class Verdict:
    outcome: str  # "beat", "lost", "tied" or "unknown" (no seed has both variants)
    sentence: str
    a: str | None = None  # the methods compared (a beat, lost to or tied with b)
    b: str | None = None
    difference: str = ""  # the paired difference in short: "+5.7%, 3.4 SEM, higher in 3 of 3"


def verdict_outcome(d: np.ndarray, warm: np.ndarray, min_difference: float, noise_sems: float) -> str:
    """'beat', 'lost' or 'tied' from the paired per-seed differences d = MAPEX - warm-up only (n,).

    n >= 2: 'beat' when mean(d) > noise_sems * SEM(d) and MAPEX is higher in more than half of
    the seeds; 'lost' the mirror image; otherwise 'tied' (inside the seed noise). n = 1: no
    noise estimate, so 'beat'/'lost' need |d| > min_difference * |warm| (warm-up only's
    hypervolume), otherwise 'tied'; with warm = 0 any nonzero difference counts.
    """
    n = len(d)
    if n == 1:
        big = abs(d[0]) > min_difference * abs(warm[0])
        return "beat" if big and d[0] > 0 else "lost" if big and d[0] < 0 else "tied"
    dm, dsem = mean_sem(d)
    beyond = abs(dm) > noise_sems * dsem
    if beyond and dm > 0 and (d > 0).sum() > n / 2:
        return "beat"
    if beyond and dm < 0 and (d < 0).sum() > n / 2:
        return "lost"
    return "tied"


def _percent(diff: float, base: float) -> str:
    return f"{diff / abs(base) * 100:+.1f}%" if base != 0 else "n/a"


def hv_verdict(
    runs: list[Run],
    min_difference: float = 0.05,
    noise_sems: float = 2.0,
    a: str = "mapex_td3",
    b: str = "warmup_only_td3",
    what: str | None = None,
) -> Verdict:
    """Did method `a` beat method `b` on re-evaluated hypervolume? (Default: MAPEX-TD3 vs its
    warm-up only ablation, i.e. did the advantage-weighted phase help.)

    Paired over the seeds that have both methods; the rule is `verdict_outcome`'s, and the
    sentence states it with the numbers: each method's mean ± SEM over those seeds, the mean
    paired difference ± its SEM (also relative to b's mean), and in how many seeds a was higher
    and lower. With one seed it says there is no noise estimate. `what` names a in the sentence.
    """
    la, lb = label(a), label(b)
    what = what or next((w for x, y, w in VERDICT_PAIRS if (x, y) == (a, b)), la)
    if what.startswith(ABLATION) and a in HYBRID_METHODS:
        # a hybrid (resolved extract.init: interpolate, as the params say: presentation.use_variants):
        # against warm-up only it differs in the start and the seeds too, so the pair is no ablation
        # of the advantage-weighted phase alone, and the sentence does not call it one
        what = f"{la}, started from interpolated weights,"
    hv = {(r.method, r.seed): r.metrics["front"]["hypervolume"] for r in runs}
    seeds = sorted(s for (v, s) in hv if v == a and (b, s) in hv)
    if not seeds:
        return Verdict(
            "unknown", f"Cannot say whether {what} beat {lb} on hypervolume: no seed has evaluated results for both."
        )
    x = np.array([hv[(a, s)] for s in seeds], dtype=float)
    y = np.array([hv[(b, s)] for s in seeds], dtype=float)
    d = x - y
    n = len(seeds)
    outcome = verdict_outcome(d, y, min_difference, noise_sems)
    iters = max(int(r.metrics["iterations"]) for r in runs if r.method in (a, b))
    tally = f"{la} was higher in {int((d > 0).sum())} of {n} seed(s), lower in {int((d < 0).sum())}"
    if n > 1:
        (am, asem), (bm, bsem), (dm, dsem) = mean_sem(x), mean_sem(y), mean_sem(d)
        z = f"{abs(dm) / dsem:.1f} SEM from zero" if dsem > 0 else "every seed's difference the same"
        numbers = (
            f"Mean ± SEM over seeds {', '.join(map(str, seeds))}: {la} {fmt_num(am)} ± {fmt_num(asem)}, "
            f"{lb} {fmt_num(bm)} ± {fmt_num(bsem)}. Paired by seed, {la} - {lb} = "
            f"{fmt_num(dm)} ± {fmt_num(dsem)} (SEM; {_percent(dm, bm)} of {lb}'s mean, {z}); {tally}."
        )
        rule = (
            f"Rule: 'beat' or 'lost to' needs the mean paired difference beyond {noise_sems:g} SEM of the "
            f"paired differences (report.noise_sems) and the same sign in more than half of the seeds; "
            f"otherwise 'tied with': inside the seed noise."
        )
    else:
        numbers = (
            f"One seed only ({seeds[0]}), so no estimate of seed noise: {la} {fmt_num(float(x[0]))}, "
            f"{lb} {fmt_num(float(y[0]))}, difference {fmt_num(float(d[0]))} "
            f"({_percent(float(d[0]), float(y[0]))}); {tally}."
        )
        rule = (
            f"Rule: with one seed, a difference within ±{min_difference * 100:g}% of {lb}'s hypervolume "
            f"(report.min_difference) counts as a tie."
        )
    if n > 1:
        z_short = f", {abs(dm) / dsem:.1f} SEM" if dsem > 0 else ""
        short = f"{_percent(dm, bm)}{z_short}, higher in {int((d > 0).sum())} of {n}"
    else:
        short = f"{_percent(float(d[0]), float(y[0]))}, one seed"
    verb = {"beat": "beat", "lost": "lost to", "tied": "tied with"}[outcome]
    text = (
        f"At this scale ({n} seed{'s' if n > 1 else ''}, up to {iters} iterations), {what} {verb} {lb} on "
        f"re-evaluated hypervolume. {numbers} {rule}"
    )
    return Verdict(outcome, text, a, b, short)


def default_pairs() -> list[tuple[str, str, str]]:
    """VERDICT_PAIRS, then each method variant of the report (pipeline.reporting.presentation.use_variants)
    against the method it varies: (a, b, what a is)."""
    extra = [(name, VARIANT_BASES[name], label(name)) for name in VARIANT_METHODS]
    return [*VERDICT_PAIRS, *extra]


def verdicts(
    runs: list[Run],
    min_difference: float = 0.05,
    noise_sems: float = 2.0,
    pairs: list[list[str]] | list[tuple[str, str]] | None = None,
) -> list[Verdict]:
    """One verdict per pair whose two methods were both run (paired by seed): of `pairs` ([a, b]
    by the methods' names, what a is: its label), or of `default_pairs()` when None."""
    present = {r.method for r in runs}
    chosen = default_pairs() if pairs is None else [(a, b, None) for a, b in pairs]
    return [
        hv_verdict(runs, min_difference, noise_sems, a, b, what)
        for a, b, what in chosen
        if a in present and b in present
    ]
