"""benchmarks.records in quick mode, end to end: two simulated quadcopters, each with a
whole agent in its own process (one recording, one without a recorder), flown for a few
seconds against the benchmark's local platform; then the report, its figures and its CPU
readings are checked for shape. Nothing about timing: the machine may be busy."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import pytest

from benchmarks import records

pytestmark = pytest.mark.cost(45)  # two simulators and two agents, about 40 s


def _number(value: Any) -> float:
    assert isinstance(value, int | float) and not isinstance(value, bool), value
    assert math.isfinite(value) and value >= 0, value
    return float(value)


def test_quick_mode_writes_the_report_its_figures_and_the_cpu_readings(tmp_path: Path) -> None:
    params = records.Params(minutes=0.2, altitude_m=5)
    records.run(params, out=tmp_path, command="pytest quick mode")

    saved = json.loads((tmp_path / "figures.json").read_text())
    assert saved["command"] == "pytest quick mode"
    assert saved["machine"]["cores"] >= 1
    figures = saved["figures"]
    assert figures["params"] == {"minutes": 0.2, "altitude_m": 5}
    assert _number(figures["session_s"]) > 0

    record = figures["record"]
    assert _number(record["bytes_per_hour"]) > 0 and record["batches"] > 0
    assert record["samples"] == sum(k["samples"] for k in record["by_kind"].values())
    kinds = record["by_kind"]
    # The drone took off and landed on commands; the agent reported events; the tlog
    # carried MAVLink both ways; telemetry came at up to 5 a second.
    for kind in ("telemetry", "command", "event", "tlog"):
        assert kinds[kind]["samples"] > 0, kind
        _number(kinds[kind]["bytes_per_hour"])
    assert kinds["telemetry"]["samples"] <= 5 * figures["session_s"] + 5
    assert kinds["dropped"]["samples"] == 0
    assert math.isclose(sum(k["share"] for k in kinds.values()), 1.0)
    assert _number(record["tlog_messages_per_s"]) > 0
    assert record["batches_left_on_disk"] == 0  # every batch acknowledged

    cpu = figures["cpu"]
    assert {"agent recording", "agent baseline", "simulator recording"} <= set(cpu["processes"])
    for process in cpu["processes"].values():
        _number(process["cpu_s"])
    assert isinstance(cpu["recording_minus_baseline_s"], float)
    assert _number(cpu["recorder_own_s"]) > 0
    assert {"raw", "sampling", "batches", "upload", "acked", "command"} <= set(
        cpu["recorder_own_by_part"]
    )
    for part in cpu["recorder_own_by_part"].values():
        assert part["calls"] > 0
    for flight in figures["flight"].values():
        assert flight["commands"]["take_off"] == 1 and flight["commands"]["land"] == 1
        assert flight["not_ok"] == {}
    assert figures["agent_logs"] == {"recording": [], "baseline": []}

    with (tmp_path / "cpu.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 2
    assert {"t_s", "agent recording", "agent baseline"} <= set(rows[0])
    for row in rows:
        for value in row.values():
            _number(float(value))

    report = (tmp_path / "README.md").read_text()
    assert report.startswith("# The flight record: size per hour")
    assert "`pytest quick mode`" in report
    for heading in ("## Size", "## CPU"):
        assert heading in report
    for kind in ("telemetry", "command", "event", "tlog"):
        assert f"| `{kind}` |" in report
    assert "nan" not in report
