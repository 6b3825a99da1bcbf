"""The suite's order for pytest-xdist (tests/scheduling.py): the same tests, the slow
modules spread over the workers' slices, each slice as long as worksteal cuts it."""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from tests.scheduling import longest_first, measured_density, measured_durations


@dataclass
class Collected:
    nodeid: str
    keywords: set[str] = field(default_factory=set)
    cost: float | None = None

    def get_closest_marker(self, name: str) -> Any:
        return SimpleNamespace(args=(self.cost,)) if name == "cost" and self.cost else None


def _suite() -> list[Collected]:
    tests: list[Collected] = []
    # Collection order: the slow modules bunched together, as the directories put them.
    for m in range(5):
        tests += [Collected(f"a/test_quick{m}.py::t{i}") for i in range(20)]
    tests += [Collected(f"b/test_rescue.py::t{i}", {"realtime"}) for i in range(4)]
    tests += [Collected(f"b/test_pages.py::t{i}", {"browser"}) for i in range(3)]
    tests += [Collected(f"b/test_limits.py::t{i}", {"realtime"}) for i in range(3)]
    tests += [Collected(f"b/test_bench.py::t{i}", {"benchmark_harness"}) for i in range(2)]
    # Two missions of a minute each, marked as such: alone in their slice.
    tests += [Collected(f"c/test_missions.py::t{i}", {"realtime"}, 60.0) for i in range(2)]
    tests += [Collected(f"d/test_quick.py::t{i}") for i in range(20)]
    return tests


def _slices(ordered: list[Collected], workers: int) -> list[list[Collected]]:
    """Cut as pytest-xdist's worksteal does: len // remaining, front first."""
    out, rest = [], list(ordered)
    for remaining in range(workers, 0, -1):
        n = len(rest) // remaining
        out.append(rest[:n])
        rest = rest[n:]
    return out


def _slow_cost(tests: list[Collected]) -> float:
    def one(t: Collected) -> float:
        if t.cost:
            return t.cost
        if "benchmark_harness" in t.keywords:
            return 15.0
        return 12.0 if t.keywords else 0.0

    return sum(one(t) for t in tests)


def test_the_same_tests_each_module_in_its_own_order() -> None:
    suite = _suite()
    ordered = longest_first(suite, 4)
    assert sorted(t.nodeid for t in ordered) == sorted(t.nodeid for t in suite)
    for module in {t.nodeid.split("::")[0] for t in suite}:
        mine = [t.nodeid for t in ordered if t.nodeid.startswith(module + "::")]
        assert mine == [t.nodeid for t in suite if t.nodeid.startswith(module + "::")]


def test_every_slice_starts_with_its_share_of_the_slow_modules() -> None:
    slices = _slices(longest_first(_suite(), 4), 4)
    costs = [_slow_cost(s) for s in slices]
    # 270 s of slow tests in all: in collection order one slice held all of it.
    assert sorted(_slow_cost(s) for s in _slices(_suite(), 4)) == [0, 0, 0, 270]
    # Longest first onto the least loaded: the missions' 120 s alone, the rest spread.
    assert sorted(costs) == [36, 48, 66, 120], costs
    for s in slices:
        slow = [t.keywords != set() for t in s]
        # Slow first, then quick: nothing slow left for the end of a slice.
        assert slow == sorted(slow, reverse=True)


def test_one_worker_or_a_tiny_run_keeps_collection_order() -> None:
    suite = _suite()
    assert longest_first(suite, 0) == suite
    assert longest_first(suite, 1) == suite
    assert longest_first(suite[:5], 4) == suite[:5]


def test_a_module_measured_slow_goes_first_whatever_its_tier(tmp_path: Path) -> None:
    """A module in no slow tier (a mission on a simulator, say) that a full run measured
    at minutes leads a slice instead of being left for the end as quick tests are."""
    suite = _suite() + [Collected(f"e/test_sim_missions.py::t{i}") for i in range(3)]
    durations = tmp_path / "durations.json"
    durations.write_text(json.dumps({"e/test_sim_missions.py": 300.0, "b/test_pages.py": 5}))
    measured = measured_durations(durations)
    assert measured == {"e/test_sim_missions.py": 300.0, "b/test_pages.py": 5.0}
    by_tier = _slices(longest_first(suite, 4), 4)
    assert not any(t.nodeid.startswith("e/") for s in by_tier for t in s[:3])
    slices = _slices(longest_first(suite, 4, measured), 4)
    leading = [[t.nodeid.split("::")[0] for t in s[:3]] for s in slices]
    assert ["e/test_sim_missions.py"] * 3 in leading, leading
    # Missing or broken: the estimates alone.
    assert measured_durations(tmp_path / "none.json") == {}
    durations.write_text("[1, 2")
    assert measured_durations(durations) == {}


def test_the_slices_run_their_busiest_modules_at_different_times(tmp_path: Path) -> None:
    """Even slices start with the modules that work the CPU hardest, odd slices end
    with them: the workers do not all fight for the cores at once and then all wait on
    real time together. Which tests each slice holds does not change."""
    suite = _suite()
    durations = tmp_path / "durations.json"
    # b/test_rescue.py and c/test_missions.py busy; b/test_limits.py a simulator
    # flying in real time; b/test_pages.py measured in an older file's form, wall alone.
    durations.write_text(
        json.dumps(
            {
                "b/test_rescue.py": {"wall_s": 48, "cpu_s": 30},
                "c/test_missions.py": {"wall_s": 120, "cpu_s": 70},
                "b/test_limits.py": {"wall_s": 36, "cpu_s": 2},
                "b/test_bench.py": {"wall_s": 30, "cpu_s": 12},
                "b/test_pages.py": 36,
            }
        )
    )
    measured, density = measured_durations(durations), measured_density(durations)
    assert measured["b/test_pages.py"] == 36.0 and "b/test_pages.py" not in density
    plain = _slices(longest_first(suite, 2, measured), 2)
    alternated = _slices(longest_first(suite, 2, measured, density), 2)
    for before, after in zip(plain, alternated, strict=True):
        assert sorted(t.nodeid for t in before) == sorted(t.nodeid for t in after)

    def modules(tests: list[Collected]) -> list[str]:
        names = [t.nodeid.split("::")[0] for t in tests if t.nodeid[0] in "bc"]
        return list(dict.fromkeys(names))

    def rate(name: str) -> float:
        return density.get(name, statistics.median_high(density.values()))

    first, second = (modules(s) for s in alternated)
    assert [rate(m) for m in first] == sorted((rate(m) for m in first), reverse=True), first
    assert [rate(m) for m in second] == sorted(rate(m) for m in second), second
    assert len(first) > 1 and len(second) > 1, (first, second)
