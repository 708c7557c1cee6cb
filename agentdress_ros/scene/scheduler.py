"""The frame-budget scheduler: which agents to dress this tick, at which level, so the tick stays inside its budget.

Pure: it sees estimated costs (measured by the scene, or injected by a test) and returns decisions; it never
measures time itself. Rule: start every agent at its distance tier; while the estimate exceeds the budget, take the
farthest agent that may be lowered and lower it one level at a time to the cheapest level, then skip it for this
tick. Agents skipped on the ticks before are lowered only after those that were not (the longest waiting last), so
over-budget far agents take turns: with room for half of them, each is updated on alternate ticks. Agents whose tier is below `protect`
(the near ones) are never lowered; when they alone exceed the budget (many near agents whose poses arrive
together), the farthest of them are deferred to the next tick, at most `near_wait` ticks in a row, so their work
spreads over the ticks between poses instead of making one tick late. An agent skipped `max_wait` ticks in a row is
not skipped again (dressed at its cheapest level), so no agent stops moving however full the tick.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

__all__ = ["Candidate", "Decision", "schedule"]


@dataclass
class Candidate:
    key: object
    distance: float
    tier: int  # the level its distance asks for
    costs: Sequence[float]  # estimated ms at each level (index = level; len = number of levels)
    waited: int = 0  # ticks in a row this agent was skipped by the budget


@dataclass
class Decision:
    key: object
    level: int | None  # None: skipped this tick
    degraded: bool  # lowered or skipped by the budget
    tier: int
    estimate: float  # ms the decision is expected to cost


def schedule(candidates: Sequence[Candidate], budget_ms: float, protect: int = 1, max_wait: int = 0,
             near_wait: int = 0) -> list[Decision]:
    """Decisions for every candidate (same order). `budget_ms` <= 0 disables the budget; `max_wait` <= 0 lets an
    agent wait indefinitely; `near_wait` is how many ticks in a row a protected agent may be deferred (0: never)."""
    level = {id(c): c.tier for c in candidates}
    skipped: set[int] = set()
    total = sum(c.costs[c.tier] for c in candidates)
    if budget_ms > 0 and total > budget_ms:
        lowerable = [c for c in candidates if c.tier >= protect]
        lowerable.sort(key=lambda c: (c.waited, -c.distance))
        for c in lowerable:
            if total <= budget_ms:
                break
            while total > budget_ms and level[id(c)] < len(c.costs) - 1:
                total += c.costs[level[id(c)] + 1] - c.costs[level[id(c)]]
                level[id(c)] += 1
            if total > budget_ms and not (max_wait > 0 and c.waited >= max_wait):
                total -= c.costs[level[id(c)]]
                skipped.add(id(c))
        if total > budget_ms and near_wait > 0:  # protected agents alone overfill the tick: defer the farthest
            near = [c for c in candidates if c.tier < protect]
            nearest = min(near, key=lambda c: c.distance) if near else None  # never deferred
            deferrable = [c for c in near if c is not nearest and c.waited < near_wait]
            deferrable.sort(key=lambda c: (c.waited, -c.distance))
            for c in deferrable:
                if total <= budget_ms:
                    break
                total -= c.costs[level[id(c)]]
                skipped.add(id(c))
    decisions = []
    for c in candidates:
        if id(c) in skipped:
            decisions.append(Decision(c.key, None, True, c.tier, 0.0))
        else:
            lv = level[id(c)]
            decisions.append(Decision(c.key, lv, lv != c.tier, c.tier, c.costs[lv]))
    return decisions
