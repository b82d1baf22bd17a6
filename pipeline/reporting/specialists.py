"""The specialists behind the fronts, judged on their own objectives: each specialist's
re-evaluated return on the objective it was trained for, per seed and kind (`own_returns`,
`own_returns_table`), and the ones too weak for a front extracted from them to be evidence
about the method (`weak_specialists`, `weak_sentence`).

A TD3 specialist is one starting policy; a PDERL specialist is its whole policy set, judged by
its best policy on its own objective. Every method of a seed and kind starts from the same
specialists, re-evaluated on the same episodes, so their numbers are read from one run each.

The rule, for the specialist of objective k, seed s and kind K, which returned v on objective k;
b is the best v over the seeds of kind K (with one seed, b = v: the fraction rule cannot fire):
- fraction f (report.weak_specialist_fraction): where b > 0, weak when v < f * b. Where b <= 0
  (an energy objective: returns <= 0) a fraction of b lies above b, so the threshold is f of the
  way up from w to b instead, w the worst return on objective k of any starting policy of any
  kind and seed (usually another objective's specialist): weak when v < w + f * (b - w).
- absolute a_k (report.weak_specialist_min_return, one per objective, null = unused): weak when
  v < a_k.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.reporting.runs import Run
from pipeline.reporting.tables import _md_table, fmt_num, specialist_runs


@dataclass(frozen=True)
class OwnReturn:
    """One specialist's re-evaluated return on its own objective."""

    kind: str  # td3 or pderl
    seed: int
    objective: int  # the objective it was trained for
    value: float  # mean return on `objective` (a policy set: its best policy's); NaN if the run holds none
    policies: int  # its starting policies in the run: 1 for TD3, the policy set's size for PDERL


@dataclass(frozen=True)
class Weakness:
    own: OwnReturn
    reasons: tuple[str, ...]  # each rule it fails, as words: "below 50% of the best TD3 seed's (1754, seed 0)"


def own_returns(runs: list[Run]) -> list[OwnReturn]:
    """Per (kind, seed) and objective k: the best return on k of the starting policies from the
    specialist of k (TD3: its one policy), read from one run of that seed and kind."""
    out = []
    for (kind, seed), r in specialist_runs(runs).items():
        objective = r.objective if r.objective is not None else np.full(len(r.origin), -1)
        for k in range(r.returns.shape[1]):
            mine = (r.origin == "specialist") & (objective == k)
            value = float(r.returns[mine, k].max()) if mine.any() else math.nan
            out.append(OwnReturn(kind, seed, k, value, int(mine.sum())))
    return out


def weak_specialists(
    runs: list[Run], fraction: float | None = 0.5, min_return: list[float | None] | None = None
) -> list[Weakness]:
    """The specialists below either threshold of the module docstring's rule, in own_returns' order."""
    own = [o for o in own_returns(runs) if math.isfinite(o.value)]
    starts = [r.returns[r.origin == "specialist"] for r in specialist_runs(runs).values()]
    out = []
    for o in own:
        k, reasons = o.objective, []
        if fraction is not None:
            best = max((p for p in own if (p.kind, p.objective) == (o.kind, k)), key=lambda p: p.value)
            of_best = f"the best {o.kind.upper()} seed's ({fmt_num(best.value)}, seed {best.seed})"
            if best.value > 0:
                threshold, text = fraction * best.value, f"below {fraction * 100:g}% of {of_best}"
            else:
                worst = min(float(s[:, k].min()) for s in starts if len(s))
                threshold = worst + fraction * (best.value - worst)
                text = (
                    f"below {fmt_num(threshold)}, {fraction * 100:g}% of the way up from the worst starting "
                    f"policy's return ({fmt_num(worst)}) to {of_best}"
                )
            if o.value < threshold:
                reasons.append(text)
        bound = min_return[k] if min_return is not None and k < len(min_return) else None
        if bound is not None and o.value < bound:
            reasons.append(f"below report.weak_specialist_min_return ({fmt_num(bound)})")
        if reasons:
            out.append(Weakness(o, tuple(reasons)))
    return out


def weak_sentence(w: Weakness, names: list[str]) -> str:
    """'Warning: the TD3 x velocity specialist (objective 0) of seed 1 returned 10 on its own objective, ...'."""
    o = w.own
    who = f"the {o.kind.upper()} {names[o.objective]} specialist (objective {o.objective}) of seed {o.seed}"
    if o.policies > 1:
        who += f", its best of {o.policies} policies,"
    return (
        f"Warning: {who} returned {fmt_num(o.value)} on its own objective, {' and '.join(w.reasons)}: "
        "fronts from it are not evidence about the method."
    )


def own_returns_table(runs: list[Run], names: list[str], weak: list[Weakness] = ()) -> str:
    """One row per kind and seed, one column per objective: the specialist's return on its own
    objective ('best of N' for a policy set, '(weak)' where `weak` names it); '' if no kind ran."""
    flagged = {(w.own.kind, w.own.seed, w.own.objective) for w in weak}
    rows: dict[tuple[str, int], list[str]] = {}
    for o in own_returns(runs):
        cell = "n/a" if not math.isfinite(o.value) else fmt_num(o.value)
        cell += f" (best of {o.policies})" if o.policies > 1 else ""
        cell += " (weak)" if (o.kind, o.seed, o.objective) in flagged else ""
        rows.setdefault((o.kind, o.seed), [o.kind.upper(), str(o.seed)]).append(cell)
    if not rows:
        return ""
    header = ["specialists", "seed", *(f"{n} (objective {k})" for k, n in enumerate(names))]
    return _md_table(header, list(rows.values()))


def sources_line(runs: list[Run], names: list[str]) -> str | None:
    """Which objectives of the imported kind were imported and which trained here, from the
    runs whose metrics record it (`specialist_sources`: imported slots beside slots trained here
    by stage train_specialist_imported): 'objectives imported: 0 (x velocity: sb3 td3, file
    speed.zip); trained here: 1 (energy: TD3, 300 steps of td3 and train_specialist)'; one such
    text per distinct set of sources (prefixed by its seeds where they differ), None if no run
    records sources."""
    texts: dict[str, list[int]] = {}
    for r in sorted(runs, key=lambda r: r.seed):
        sources = r.metrics.get("specialist_sources")
        if not sources:
            continue
        imported, trained = [], []
        for s in sources:
            k = int(s["objective"])
            name = names[k] if k < len(names) else f"objective {k}"
            if "trained" in s:
                steps = f", {s['total_steps']} steps" if s.get("total_steps") is not None else ""
                trained.append(
                    f"{k} ({name}: {str(s['trained']).upper()}{steps} with the td3 and train_specialist settings)"
                )
            else:
                src = s.get("imported") or {}
                what = " ".join(str(src[key]) for key in ("format", "algorithm") if src.get(key))
                imported.append(f"{k} ({name}: {what or 'imported'}, file {src.get('file')})")
        text = f"objectives imported: {', '.join(imported) or 'none'}; trained here: {', '.join(trained)}"
        seeds = texts.setdefault(text, [])
        if r.seed not in seeds:
            seeds.append(r.seed)
    if not texts:
        return None
    if len(texts) == 1:
        return next(iter(texts))
    return "; ".join(
        f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}: {text}" for text, seeds in texts.items()
    )
