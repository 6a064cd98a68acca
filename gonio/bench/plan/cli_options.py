"""``gonio capture``'s sequential-plan options as a ``[strategy]`` table: ``--plan adaptive`` or
``ndf`` with ``--points``, ``--budget-minutes``, ``--target-rel-u``, ``--target-de00``,
``--candidates`` and ``--criterion`` (gonio.bench.plan.adaptive's keys), checked in one line each."""

from __future__ import annotations

import math
from typing import Any

from gonio.bench.plan.adaptive import CRITERIA

__all__ = ["CLI_STOPS", "SEQUENTIAL", "cli_strategy"]

#: The stops of ``gonio capture --plan adaptive``: (flag, [strategy] key, what a value is, its unit).
CLI_STOPS = (("--points", "points", "the most points", ""),
             ("--budget-minutes", "budget_s", "the most instrument time", " minutes"),
             ("--target-rel-u", "target_rel_u", "a relative 1-sigma", ""),
             ("--target-de00", "target_de00", "a CIEDE2000 colour difference", ""))


#: ``--plan`` names that are strategies drawing from ``--candidates``: the D-optimal sequential
#: design (this module) and the NDF-seeded plan (gonio.bench.plan.ndf_seeded)
SEQUENTIAL = ("adaptive", "ndf")


def cli_strategy(plan: str, *, points: int | None, target_rel_u: float | None, candidates: str | None,
                 seed: int, budget_minutes: float | None = None, target_de00: float | None = None,
                 criterion: str | None = None) -> tuple[str, dict | None]:
    """``gonio capture``'s plan options as (the plan to load, the ``[strategy]`` table): ``--plan
    adaptive`` (or ``ndf``, :data:`SEQUENTIAL`) draws from ``--candidates`` (default the ``dense`` preset) and stops at ``--points``
    or ``--budget-minutes`` (not both) or its targets; ``--criterion`` (:data:`CRITERIA`) chooses
    the adaptive plan's batches (ndf places its own); a fixed plan takes none of the adaptive
    options. ValueError, one line naming the option, for a value that is not > 0 and finite."""
    given = dict(zip([k for _, k, _, _ in CLI_STOPS], (points, budget_minutes, target_rel_u, target_de00)))
    if plan not in SEQUENTIAL:
        for flag, v in (("--points", points), ("--budget-minutes", budget_minutes), ("--target-rel-u", target_rel_u),
                        ("--target-de00", target_de00), ("--candidates", candidates), ("--criterion", criterion)):
            if v is not None:
                raise ValueError(f"{flag} goes with --plan adaptive")
        return plan, None
    for flag, key, what, unit in CLI_STOPS:
        v = given[key]
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0) or (
                key == "points" and v != int(v)):
            raise ValueError(f"{flag} {v!r}: give {what} as a number > 0{unit and ' (' + unit.strip() + ')'}")
        if unit and not v <= 1e6:
            raise ValueError(f"{flag} {v!r}: more than a million minutes; give {what} in minutes")
    if points is not None and budget_minutes is not None:
        raise ValueError("--points and --budget-minutes exclude each other: give the most points or the most "
                         "instrument time")
    if criterion is not None and (plan != "adaptive" or criterion not in CRITERIA):
        raise ValueError(f"--criterion {str(criterion)[:40]!r}: give one of {', '.join(CRITERIA)}, with --plan adaptive"
                         " (ndf places its points by its own rule)")
    table: dict[str, Any] = {"name": plan, "seed": int(seed)}
    if criterion is not None:
        table["criterion"] = criterion
    if points is not None:
        table["points"] = int(points)
    if budget_minutes is not None:
        table["budget_s"] = float(budget_minutes) * 60.0
        table["points"] = 0                 # as many as the time allows
    if target_rel_u is not None:
        table["target_rel_u"] = float(target_rel_u)
    if target_de00 is not None:
        table["target_de00"] = float(target_de00)
    return candidates or "dense", table
