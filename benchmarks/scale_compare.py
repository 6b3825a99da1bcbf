"""Scale benchmark runs side by side: the figures of several ``summary.json`` files of
``benchmarks.scale`` in one table, a column per run.

``python -m benchmarks.scale --baseline REF`` and ``--servers daphne,uvicorn`` write
this report themselves (:func:`compare_md`) beside one folder per run. Runs made
separately can be put side by side afterwards::

    python -m benchmarks.scale_compare before=old/summary.json after=new/summary.json \\
        [--out report.md]
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

#: The issue's targets ("control plane at fleet scale"), shown beside the figures they
#: are about.
TARGET_MS_PER_HEARTBEAT = 0.15
TARGET_CPU_PCT_5000_AT_1HZ = 80.0
TARGET_SESSIONS_PER_S = 30.0
TARGET_REQUEST_P95_MS = 100.0
TARGET_RELAY_P95_MS = 20.0
#: The production shape's issue: the API while a login flood runs.
TARGET_FLOOD_API_P95_MS = 200.0


def _get(data: dict[str, Any], *path: str | int) -> Any:
    """``data[path[0]][path[1]]...``, None where any step is missing."""
    value: Any = data
    for key in path:
        try:
            value = value[key]
        except (KeyError, IndexError, TypeError):
            return None
    return value


def _num(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}f}"


def _pair(s: Any, a: str = "p50", b: str = "p95") -> str:
    if not s or not s.get("n"):
        return "n/a"
    return f"{_num(s[a])} / {_num(s[b])}"


Row = tuple[str, Callable[[dict[str, Any]], str], str]


def _api_load(run: dict[str, Any]) -> str:
    """How the run drove the API: a closed loop, or a pace (runs before pacing have no
    rate: a closed loop)."""
    clients = _num(_get(run, "params", "api_clients"), 0)
    rate = _get(run, "params", "api_rate")
    return f"{clients} clients, " + (f"{rate:g} sessions/s paced" if rate else "closed loop")


def _rows(runs: Sequence[dict[str, Any]]) -> list[Row]:
    """(label, cell of one run's summary, target) for each line of the table; the stage
    rows come from every agent count any run measured."""
    counts = sorted({st["agents"] for r in runs for st in _get(r, "figures", "stages") or []})

    def fig(*path: str | int, digits: int = 1) -> Callable[[dict[str, Any]], str]:
        return lambda r: _num(_get(r, "figures", *path), digits)

    def online(r: dict[str, Any]) -> str:
        a = _get(r, "figures", "agents") or {}
        return f"{_num(a.get('online_min'))} of {_num(a.get('n'))}"

    rows: list[Row] = [
        ("topology", lambda r: str(_get(r, "machine", "topology") or "single"), ""),
        ("ASGI server", lambda r: str(_get(r, "machine", "server") or "daphne"), ""),
        ("platform code", lambda r: str(_get(r, "machine", "platform_code") or "?"), ""),
        ("heartbeat interval (s)", lambda r: _num(_get(r, "machine", "heartbeat_s"), 1), ""),
        ("light agents", fig("agents", "n"), ""),
        ("API load", _api_load, ""),
        ("idle process: CPU % of one core", fig("agents", "idle_cpu_pct"), ""),
        ("with all agents: CPU % of one core", fig("agents", "cpu_pct"), ""),
        ("with all agents: RSS MB", fig("agents", "rss_mb", digits=0), ""),
        ("heartbeats sent per s", fig("agents", "heartbeats_per_s", digits=0), ""),
        (
            "**platform CPU per heartbeat (ms)**",
            fig("agents", "cpu_ms_per_heartbeat", digits=3),
            f"≤ {TARGET_MS_PER_HEARTBEAT}",
        ),
        (
            "CPU per heartbeat over idle (ms)",
            fig("agents", "cpu_ms_per_heartbeat_over_idle", digits=3),
            "",
        ),
        ("CPU % per agent", fig("agents", "cpu_pct_per_agent", digits=3), ""),
        ("KiB per agent", fig("agents", "rss_kb_per_agent", digits=0), ""),
        ("online at least (whole window)", online, "all"),
        (
            "heartbeat age p50 / p95 (s)",
            lambda r: _pair(
                _get(
                    r,
                    "figures",
                    "fleet",
                    f"one/{_get(r, 'params', 'agents')} agents",
                    "heartbeat_age_s",
                )
            ),
            "",
        ),
        ("vehicle rows updated per s", fig("agents", "vehicle_updates_per_s", digits=0), ""),
    ]
    for count in counts:
        rows.append((f"{count} agents: CPU % / ms per heartbeat", _stage_pair(count), ""))
    for topology, name in (("one", "API load"), ("two", "phase 4, two processes")):
        if not any(_get(r, "figures", "api", topology) for r in runs):
            continue
        api = ("figures", "api", topology)
        first = topology == "one"
        rows += [
            (
                f"{name}: sessions per s",
                _num_at(*api, "sessions_per_s"),
                f"≥ {TARGET_SESSIONS_PER_S:g}" if first else "",
            ),
            (
                f"{name}: request p50 / p95 (ms)",
                _pair_at(*api, "request_ms"),
                f"p95 ≤ {TARGET_REQUEST_P95_MS:g}" if first else "",
            ),
            (f"{name}: end p50 / p95 (ms)", _pair_at(*api, "end_ms"), ""),
            (f"{name}: task delivery p50 / p95 (ms)", _pair_at(*api, "task_delivery_ms"), ""),
            (
                f"{name}: relayed round trip p50 / p95 (ms)",
                _pair_at("figures", "relay", topology),
                f"p95 ≤ {TARGET_RELAY_P95_MS:g}",
            ),
            (f"{name}: relayed commands lost", _num_at("figures", "relay", topology, "lost"), "0"),
        ]
    phases = ["API load", "login flood: during"]
    if any(_get(r, "figures", "roles", p) for r in runs for p in phases):
        for phase in phases:
            rows.append((f"{phase}: CPU % by role", _roles(phase), ""))
    if any(_get(r, "figures", "flood") for r in runs):
        flood = ("figures", "flood")
        rows += [
            ("login flood: clients / attempts per s", _flood_load, ""),
            ("login flood: attempts answered", _flood_answers, ""),
        ]
        for window in ("without", "during"):
            rows += [
                (
                    f"{window} the flood: `GET /api/v1/services` p50 / p95 (ms)",
                    _pair_at(*flood, "api", window, "services_ms"),
                    f"p95 ≤ {TARGET_FLOOD_API_P95_MS:g}" if window == "during" else "",
                ),
                (
                    f"{window} the flood: session request p50 / p95 (ms)",
                    _pair_at(*flood, "api", window, "request_ms"),
                    "",
                ),
                (
                    f"{window} the flood: every API call p50 / p95 (ms)",
                    _pair_at(*flood, "api", window, "all_ms"),
                    f"p95 ≤ {TARGET_FLOOD_API_P95_MS:g}" if window == "during" else "",
                ),
            ]
    if any(_get(r, "figures", "fleet_phase") for r in runs):
        rows.append(("fleet phase: online at least", _fleet_online, "all"))
    modes = sorted({k for r in runs for k in (_get(r, "figures", "reaction") or {})})
    for key in modes:
        rows.append(
            (
                f"link loss to stop, {key.replace('/', ': ').replace('_', ' ')}: p50 / p95 (ms)",
                _pair_at("figures", "reaction", key, "reaction_ms"),
                "",
            )
        )
    for label in ("tracebacks", "errors logged (ERROR)"):
        rows.append((f"platform logs: {label}", _log_total(label), "0"))
    return rows


def _roles(phase: str) -> Callable[[dict[str, Any]], str]:
    """A window's CPU (% of one core) per role: "gunicorn 40 / uvicorn 20 / ..."."""

    def cell(r: dict[str, Any]) -> str:
        by = _get(r, "figures", "roles", phase) or {}
        short = {k: k.removeprefix("platform: ").split(" (")[0] for k in by}
        return " / ".join(f"{short[k]} {by[k]:.0f}" for k in by) or "n/a"

    return cell


def _flood_load(r: dict[str, Any]) -> str:
    flood = _get(r, "figures", "flood")
    if not flood:
        return "n/a"
    return f"{flood['clients']} / {flood['attempts_per_s']:.1f}"


def _flood_answers(r: dict[str, Any]) -> str:
    answers = _get(r, "figures", "flood", "answers")
    if answers is None:
        return "n/a"
    return ", ".join(f"{k}: {v}" for k, v in sorted(answers.items())) or "none"


def _fleet_online(r: dict[str, Any]) -> str:
    fleet = _get(r, "figures", "fleet_phase")
    if not fleet:
        return "n/a"
    return f"{_num(fleet.get('online_min'))} of {_num(fleet.get('agents'))}"


def _num_at(*path: str | int, digits: int = 1) -> Callable[[dict[str, Any]], str]:
    return lambda r: _num(_get(r, *path), digits)


def _pair_at(*path: str | int) -> Callable[[dict[str, Any]], str]:
    return lambda r: _pair(_get(r, *path))


def _log_total(label: str) -> Callable[[dict[str, Any]], str]:
    """Lines matching ``label`` in all of a run's platform processes' logs."""
    return lambda r: _num(sum(c.get(label, 0) for c in (_get(r, "platform_logs") or {}).values()))


def _stage_pair(count: int) -> Callable[[dict[str, Any]], str]:
    def cell(r: dict[str, Any]) -> str:
        for st in _get(r, "figures", "stages") or []:
            if st["agents"] == count:
                return f"{_num(st.get('cpu_pct'), 0)} / {_num(st.get('cpu_ms_per_heartbeat'), 3)}"
        return "n/a"

    return cell


def compare_md(runs: Sequence[tuple[str, str, dict[str, Any]]], *, command: str = "") -> str:
    """The side-by-side report of ``runs``: (label, folder of its full report, its
    summary.json) each, in the order they ran."""
    lines = ["# Scale benchmark: runs side by side", ""]
    if command:
        lines += [f"Generated by `{command}` (`benchmarks/scale.py`).", ""]
    if any(_get(r, "params", "quick") for _, _, r in runs):
        lines += ["**Quick mode: a smoke test of the benchmark, not a measurement.**", ""]
    lines += [
        "One run per column, one after the other on the same machine, with the same "
        "parameters and the same load generators (this checkout's light agents, API clients "
        "and cars); what changes is the platform's code (a `git worktree` of the baseline, "
        "migrated from nothing), its ASGI server or its topology (one process, or the "
        "production shape: gunicorn and uvicorn processes). Every platform process ran "
        "behind nginx. Each run's full report, its CSVs and its notes are in its folder.",
        "",
    ]
    labels = [f"[{label}]({folder}/report.md)" for label, folder, _ in runs]
    lines.append("| | " + " | ".join(labels) + " | target |")
    lines.append("|---|" + "---:|" * len(runs) + "---|")
    for label, cell, target in _rows([r for _, _, r in runs]):
        lines.append(f"| {label} | " + " | ".join(cell(r) for _, _, r in runs) + f" | {target} |")
    lines += [
        "",
        "*Platform CPU per heartbeat*: the platform process's CPU seconds over the window "
        "with all agents connected, divided by the heartbeats the agents sent in it; the "
        "targets are the issue's (5,000 agents at one heartbeat per second at ≤ "
        f"{TARGET_CPU_PCT_5000_AT_1HZ:g} % of one core; sessions and request p95 with 1,000 "
        "agents online; relayed p95 under that API load).",
        "",
    ]
    notes = [(label, n) for label, _, r in runs for n in r.get("notes", [])]
    if notes:
        lines += ["## Notes from the runs", ""]
        seen: set[tuple[str, str]] = set()
        for label, note in notes:
            if (label, note) not in seen:
                seen.add((label, note))
                lines.append(f"* {label}: {note}")
        lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.scale_compare",
        description="Put summary.json files of benchmarks.scale side by side.",
    )
    parser.add_argument("runs", nargs="+", help="LABEL=path/to/summary.json, in column order")
    parser.add_argument("--out", type=Path, help="write the report here (default: print it)")
    args = parser.parse_args(argv)
    runs = []
    for item in args.runs:
        label, sep, path = item.partition("=")
        if not sep:
            parser.error(f"{item!r}: expected LABEL=path/to/summary.json")
        summary_path = Path(path)
        # The links to each run's report are relative to where this report goes.
        where = args.out.resolve().parent if args.out else Path.cwd()
        folder = os.path.relpath(summary_path.resolve().parent, where)
        runs.append((label, folder, json.loads(summary_path.read_text())))
    text = compare_md(runs)
    if args.out:
        args.out.write_text(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
