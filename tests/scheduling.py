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

Within its slice, a module's place also follows how hard it works the CPU while it
runs (its measured CPU over wall time): the even slices run their busiest modules
first, the odd ones last. Otherwise every worker started on the costliest modules (a
rescue, a survey, the production shape) at once, fighting for the two cores, and later
all waited together on simulators flying in real time: over an idle run the machine
stood 21 % idle, in stretches of minutes at 40-80 %.
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


def _measured(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def measured_durations(path: Path = DURATIONS) -> dict[str, float]:
    """Module -> measured seconds, from ``path`` (none if it is missing or unreadable:
    the estimates by tier then order everything). An entry is ``{"wall_s", "cpu_s"}``
    or, as earlier files have it, the wall time alone."""
    walls: dict[str, float] = {}
    for name, value in _measured(path).items():
        wall = value.get("wall_s") if isinstance(value, dict) else value
        if isinstance(wall, int | float) and not isinstance(wall, bool):
            walls[str(name)] = float(wall)
    return walls


def measured_density(path: Path = DURATIONS) -> dict[str, float]:
    """Module -> its measured CPU seconds per second of wall time, for the entries of
    ``path`` that have both."""
    density: dict[str, float] = {}
    for name, value in _measured(path).items():
        if isinstance(value, dict):
            wall, cpu = value.get("wall_s"), value.get("cpu_s")
            if isinstance(wall, int | float) and isinstance(cpu, int | float) and wall > 0:
                density[str(name)] = cpu / wall
    return density


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
    items: Sequence[T],
    workers: int,
    measured: Mapping[str, float] | None = None,
    density: Mapping[str, float] | None = None,
) -> list[T]:
    """``items`` reordered for ``workers`` worksteal slices of equal length (see the
    module); the same items, each module's in its own order. ``measured``: modules'
    measured seconds, which replace their estimates; ``density``: modules' measured CPU
    per wall second (a module without one counts as the median's, the upper of two)."""
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
    placed: list[list[str]] = [[] for _ in range(workers)]  # each slice's slow modules
    size = [0] * workers
    load = [0.0] * workers
    for name in slow:
        # The least loaded slice that still has room for the whole module.
        fits = [k for k in range(workers) if size[k] + len(modules[name]) <= lengths[k]]
        k = min(fits or range(workers), key=lambda k: load[k])
        placed[k].append(name)
        size[k] += len(modules[name])
        load[k] += costs[name]
    if density:
        _alternate_by_density(placed, density)
    slices = [[t for name in names for t in modules[name]] for names in placed]
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


def _alternate_by_density(placed: list[list[str]], density: Mapping[str, float]) -> None:
    """Reorder each slice's modules by CPU density: busiest first in the even slices,
    last in the odd ones (see the module)."""
    known = sorted(density.values())
    typical = known[len(known) // 2]
    for k, names in enumerate(placed):
        names.sort(key=lambda name: density.get(name, typical), reverse=k % 2 == 0)
