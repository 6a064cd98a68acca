"""How a capture chooses its next point, declared once: the plan strategy.

A strategy draws from a plan's points (the candidates, each with its stage pose) and says
which to measure: :meth:`PlanStrategy.first` before the first move, :meth:`PlanStrategy.more`
after each journalled point, given every result so far. A fixed plan (:class:`FixedPlan`:
the move-ordered plan, every point once) asks for nothing more; an adaptive one asks for the
candidates the data says are worth it, up to its :attr:`~PlanStrategy.budget`. The run
(`gonio.bench.session.run`) reads only this protocol; session.toml's ``[strategy]`` table
names the strategy (:data:`STRATEGIES`), so a resume replays the same one.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from gonio.bench.plan.plans import Plan

__all__ = ["PlanStrategy", "FixedPlan", "STRATEGIES", "strategy_from_doc", "register_strategy"]

#: One measured point as a strategy sees it: (f_r per channel, its 1-sigma per channel).
Result = tuple[np.ndarray, np.ndarray]


@runtime_checkable
class PlanStrategy(Protocol):
    """What the capture loop asks a strategy (see the module notes)."""

    name: str
    plan: Plan

    @property
    def budget(self) -> int:
        """The most points the strategy will measure (the progress bar's total)."""

    def first(self, done: set[int]) -> list[int]:
        """The points to measure first, in order, none of ``done`` (already journalled)."""

    def more(self, results: Mapping[int, Result], queued: Sequence[int]) -> list[int]:
        """Points to add after ``queued`` (measured or about to be), given every journalled
        result so far; [] when the strategy has nothing to add. The stages move to the next
        queued point while the last one reduces, so ``results`` may lag ``queued`` by one."""

    def to_dict(self) -> dict[str, Any]:
        """session.toml's ``[strategy]`` table (:func:`strategy_from_doc` reads it back)."""

    # Optional: ``state() -> dict``, why the strategy stopped and what it knows; the run journals
    # it as a ``strategy`` event when the strategy asks for nothing more. ``use_session(stage_deg,
    # settings)``: the poses the run moves to (session.toml's order) and its settings, given by
    # `strategy_from_doc` where the doc has them (a strategy that counts time estimates the moves).


class FixedPlan:
    """Every point of the plan once, in the move order chosen before the first move."""

    name = "fixed"

    def __init__(self, plan: Plan, order: Sequence[int]):
        self.plan = plan
        self.order = [int(i) for i in order]

    @property
    def budget(self) -> int:
        return len(self.plan)

    def first(self, done: set[int]) -> list[int]:
        return [i for i in self.order if i not in done]

    def more(self, results: Mapping[int, Result], queued: Sequence[int]) -> list[int]:
        return []

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name}


#: Strategies by the name session.toml records: ``make(plan, order, table) -> PlanStrategy``.
STRATEGIES: dict[str, Callable[[Plan, Sequence[int], Mapping], PlanStrategy]] = {
    "fixed": lambda plan, order, table: FixedPlan(plan, order),
}


def register_strategy(name: str, make: Callable[[Plan, Sequence[int], Mapping], PlanStrategy]) -> None:
    """Add a strategy under ``name`` (what ``[strategy] name`` selects)."""
    STRATEGIES[name] = make


def strategy_from_doc(doc: Mapping, plan: Plan) -> PlanStrategy:
    """The strategy session.toml records (a session without ``[strategy]`` is a fixed plan);
    ValueError naming the known strategies for an unknown one."""
    table = doc.get("strategy") or {"name": "fixed"}
    name = table.get("name", "fixed") if isinstance(table, Mapping) else None
    if name not in STRATEGIES:
        raise ValueError(f"unknown plan strategy {str(name)[:40]!r}; known: {', '.join(sorted(STRATEGIES))}")
    order = doc["order"]["order"]
    strategy = STRATEGIES[name](plan, order, table)
    use = getattr(strategy, "use_session", None)
    if callable(use) and doc["order"].get("stage_deg") is not None:
        use(doc["order"]["stage_deg"], doc.get("settings"))
    return strategy
