"""What each test costs the machine in CPU, for making the suite faster.

On two cores the suite is bound by CPU, not by its longest test: its wall time is about
its CPU time over the cores, whatever the number of workers. With
``IOUV_TEST_CPU_REPORT=<file>`` every worker appends one JSON line per test to the file:
``{"test", "worker", "wall_s", "cpu_s"}``, where ``cpu_s`` is what the worker process
used during the test (set-up, call and teardown) plus what its child processes that
ended meanwhile used (the servers, agents, simulators and browsers the test started
and stopped; a module's shared ones count in the test during which they stopped).
``python -m tests.cpu_report <file>`` prints the sums per file and the costliest tests;
``python -m tests.cpu_report --durations <file> > tests/durations.json`` writes the
measured wall and CPU time of each slow module, which the suite's order reads
(tests/scheduling.py).
"""

from __future__ import annotations

import collections
import json
import os
import resource
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

_PATH = os.environ.get("IOUV_TEST_CPU_REPORT")


def _cpu_s() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    if not _PATH:
        yield
        return
    wall, cpu = time.monotonic(), _cpu_s()
    yield
    line = {
        "test": item.nodeid,
        "worker": os.environ.get("PYTEST_XDIST_WORKER", "main"),
        "wall_s": round(time.monotonic() - wall, 3),
        "cpu_s": round(_cpu_s() - cpu, 3),
    }
    # One short line per write, appended: the workers' lines do not interleave.
    with open(_PATH, "a") as out:
        out.write(json.dumps(line) + "\n")


def main(path: str, top: int = 40) -> None:
    """Print the CPU per test file and the ``top`` costliest tests of the report."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line]
    by_file: collections.Counter[str] = collections.Counter()
    for row in rows:
        by_file[row["test"].split("::")[0]] += row["cpu_s"]
    total = sum(by_file.values())
    print(f"{len(rows)} tests, {total:.0f} CPU s in all")
    for name, cpu in by_file.most_common(top):
        print(f"{cpu:8.1f}  {100 * cpu / total:5.1f} %  {name}")
    print()
    for row in sorted(rows, key=lambda r: -r["cpu_s"])[:top]:
        print(f"{row['cpu_s']:8.1f}  wall {row['wall_s']:6.1f}  {row['test']}")


def durations(path: str, *, at_least_s: float = 5.0) -> dict[str, dict[str, float]]:
    """Each module's wall time and CPU time in the report (the sums of its tests'), for
    the modules of ``at_least_s`` or more of wall time, longest first."""
    wall: collections.Counter[str] = collections.Counter()
    cpu: collections.Counter[str] = collections.Counter()
    for line in Path(path).read_text().splitlines():
        if line:
            row = json.loads(line)
            name = row["test"].split("::")[0]
            wall[name] += row["wall_s"]
            cpu[name] += row["cpu_s"]
    return {
        name: {"wall_s": round(s, 1), "cpu_s": round(cpu[name], 1)}
        for name, s in wall.most_common()
        if s >= at_least_s
    }


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--durations":
        print(json.dumps(durations(sys.argv[2]), indent=1))
    elif len(sys.argv) == 2:
        main(sys.argv[1])
    else:
        sys.exit("usage: python -m tests.cpu_report FILE | --durations FILE")
