"""The order the suite's tests are handed to pytest-xdist's workers: longest first.

pytest-xdist's ``worksteal`` scheduler gives each of ``n`` workers one contiguous
slice of the collected tests (the same number of tests each) and, when a worker runs
out, moves half of the longest remaining queue's tail to it. In collection order the
slow modules (real servers, simulators on the wall clock, browsers) bunch up in a few
slices, so the run ends with one worker going through minutes of them while the others
wait; stealing cannot split a single long test.

:func:`longest_first` lays the tests out so that each slice starts with its share of
the slow modules, balanced by their estimated cost (longest first onto the least
loaded slice), and ends with quick tests that the stealing evens out. A module's tests
stay together, in their own order, so a module-scoped fixture is set up once per
worker that runs it. A module's cost is its wall time measured in a full run
(``tests/durations.json``, written by ``python -m tests.cpu_report --durations``), or,
for a module not measured there, estimated by tier (:data:`COST_S`, markers set in
conftest.TIERS or by the module) or by its own ``pytest.mark.cost(seconds)``: only the
order changes, never which tests run. Estimates by tier alone were far off (a module of
missions on a simulator, out of every tier, counted as quick and ran last, for minutes,
on one worker while the others had finished).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol, TypeVar

#: Rough seconds a test takes by tier (its most expensive marker): what counts is the
#: ratio between tiers, not the figures, which a loaded machine multiplies anyway.
COST_S: dict[str, float] = {
    "realtime": 12.0,
    "browser": 12.0,
    "benchmark_harness": 15.0,
}

#: A test in no slow tier.
QUICK_S = 0.3

#: The measured wall times of the slow modules (see the module docstring).
DURATIONS = Path(__file__).with_name("durations.json")


def measured_durations(path: Path = DURATIONS) -> dict[str, float]:
    """Module -> measured seconds, from ``path`` (none if it is missing or unreadable:
    the estimates by tier then order everything)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict):
        return {}
    return {str(k): float(v) for k, v in data.items() if isinstance(v, int | float)}


class Keyed(Protocol):
    """What the ordering reads of a collected test (a pytest Item has both)."""

    nodeid: str
    keywords: Any

    def get_closest_marker(self, name: str) -> Any: ...


T = TypeVar("T", bound=Keyed)


def cost_s(item: Keyed) -> float:
    """The estimated cost of one test: its ``cost`` marker's, or the most expensive
    tier's it is in."""
    own = item.get_closest_marker("cost")
    if own is not None:
        return float(own.args[0])
    return max(
        (cost for marker, cost in COST_S.items() if marker in item.keywords),
        default=QUICK_S,
    )


def longest_first(
    items: Sequence[T], workers: int, measured: Mapping[str, float] | None = None
) -> list[T]:
    """``items`` reordered for ``workers`` worksteal slices of equal length (see the
    module); the same items, each module's in its own order. ``measured``: modules'
    measured seconds, which replace their estimates."""
    if workers < 2 or len(items) < 2 * workers:
        return list(items)
    modules: dict[str, list[T]] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::", 1)[0], []).append(item)
    measured = measured or {}
    costs = {
        name: measured.get(name, sum(cost_s(i) for i in tests)) for name, tests in modules.items()
    }
    slow = sorted(
        (name for name, tests in modules.items() if costs[name] > QUICK_S * len(tests)),
        key=lambda name: -costs[name],
    )
    quick = [name for name in modules if name not in set(slow)]
    # The slices' lengths as worksteal cuts them: len // remaining, front first.
    lengths: list[int] = []
    left = len(items)
    for remaining in range(workers, 0, -1):
        lengths.append(left // remaining)
        left -= lengths[-1]
    slices: list[list[T]] = [[] for _ in range(workers)]
    load = [0.0] * workers
    for name in slow:
        # The least loaded slice that still has room for the whole module.
        fits = [k for k in range(workers) if len(slices[k]) + len(modules[name]) <= lengths[k]]
        k = min(fits or range(workers), key=lambda k: load[k])
        slices[k].extend(modules[name])
        load[k] += costs[name]
    # Quick tests fill every slice up to its length, in collection order; a slice a
    # slow module overfilled passes its excess on (the lengths must add up exactly).
    rest = [t for name in quick for t in modules[name]]
    for k in range(workers):
        while len(slices[k]) > lengths[k]:
            rest.insert(0, slices[k].pop())
    ordered: list[T] = []
    for k in range(workers):
        take = lengths[k] - len(slices[k])
        slices[k].extend(rest[:take])
        del rest[:take]
        ordered.extend(slices[k])
    return ordered + rest
