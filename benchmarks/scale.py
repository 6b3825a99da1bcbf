"""Scale of the platform: thousands of agents, assignment and deployment throughput,
link loss to safe action, a login flood, and one platform process against the
production shape.

    python -m benchmarks.scale [--quick] [--agents 1000] [--out docs/benchmarks/scale]
        [--topology single|production] [--topologies single,production]
        [--server uvicorn|daphne] [--servers uvicorn,daphne] [--baseline REF]
        [--phases all|one|heartbeats] [--heartbeat-s 1] [--api-rate 30]
        [--flood-clients 4] [--flood-duration 20] [--fleet-agents 5000]
        [--web 1] [--web-workers 2] [--web-threads 4] [--ws 2]

The paired run of the production shape against one process (issue 39; the command,
its duration and what it reports: docs/benchmarks/scale/README.md)::

    python -m benchmarks.scale --topologies single,production --phases one \
        --agents 1000 --api-rate 30 --api-duration 60 --flood-duration 30 \
        --fleet-agents 5000 --heartbeat-s 1 --out docs/benchmarks/scale/production-shape

Everything on the platform side is real, started by :mod:`benchmarks.scale_topology`
behind nginx with the shipped site (``deploy/nginx/iouv.conf``: TLS, routing by path,
per-address limits): in the ``single`` topology one ASGI process (uvicorn as
``python -m iouv.serve`` runs it, the default; or daphne: ``--server``) serves
everything; in ``production`` gunicorn (``deploy/gunicorn.conf.py``) serves HTTP and
uvicorn processes the WebSockets, each started from its ``deploy/systemd`` unit's
command line; both run the Celery worker and beat of those units. They share
PostgreSQL (the benchmark's own database, ``iouv_bench_scale`` unless
``--database-url`` says otherwise, created, migrated and emptied at the start) and
Redis (``REDIS_URL``, else database 4, with its own ``CHANNELS_PREFIX``); the
platform's own signing key, vehicles registered in the database with real
credentials, API tokens, sessions assigned and deployed by the platform's code. What
is light is the load:

* **Light agents**: each is the real :class:`agents.uplink.Uplink` client (hello,
  profile, heartbeats at the interval the platform's ``welcome`` asks for, websockets'
  keepalive pings, reconnection with backoff), from a loopback address of its own
  (nginx limits connections per address, as it would for a fleet). Tasks are verified
  with the platform's public key and answered ``task_accepted``; ``end_task`` is
  answered ``task_ended``. There is no adapter and no video behind them. Many run per
  process, in a few ``--agent-worker`` processes, so the load generator is not the
  bottleneck (its CPU is measured and reported). They count the heartbeats they send:
  the platform's CPU per heartbeat is its CPU over a window divided by the heartbeats
  sent in it.
* **Cars**: two full agents (:class:`agents.runtime.Agent`, the car adapter on
  gpiozero mock pins and its simulated world) in this process, for the link-loss
  trials and the relayed control session.
* **API clients**: threads in an ``--api-worker`` process, each with its own user,
  bearer token and address, requesting a session (assignment, signed task deployed to
  a live light agent) and ending it, in a closed loop, or paced (``--api-rate``: the
  clients together start that many sessions a second, evenly spaced).
* **Login flood**: threads in a ``--flood-worker`` process, each from its own
  address, posting wrong passwords to the portal's login as fast as they are answered
  (nginx's ``limit_req`` and django-axes' lockout answer them; what each attempt got
  is counted).

Phases (the report names them; ``--phases heartbeats`` runs the first only, ``one``
all but the fourth, ``all`` the fourth too in the single topology):

1. CPU and memory idle, then with N agents connected and heartbeating (and whether
   all N are online as the platform counts them), CPU summed per role (the platform's
   processes, nginx, Celery);
2. assignment + deployment throughput under that load, with a relayed control session
   running beside it (command round trips through the platform);
3. link loss to safe action, with the N agents still connected: a controller goes
   silent (the agent's watchdog fires after the task's ``link_loss_timeout_ms``) or its
   socket dies (closed abruptly, no WebSocket close handshake), directly and through
   the relay;
4. (single topology, ``--phases all``) two platform processes behind the same nginx,
   the WebSockets on one and HTTP on the other: the agents reconnect through the
   restarted nginx, then phases 2 and the relayed part of 3 run again;
5. the login flood (``--flood-clients``, 0 for none): the API clients, each turn also
   reading the catalogue, for ``--flood-duration`` alone, then as long again during
   the flood;
6. (``--fleet-agents``) the fleet grown to that many agents, heartbeats only: all
   online? CPU per heartbeat.

The platform's database is written and read by the platform's own code
(:mod:`benchmarks.scale_probe`, in a child process), so ``--baseline REF`` can run the
same benchmark against REF's platform, from a ``git worktree`` (same virtualenv, the
database dropped and migrated by REF), then against the current code;
``--servers daphne,uvicorn`` runs it under each server in turn and
``--topologies single,production`` in each topology: each run's outputs go to a
folder of its own under ``--out`` and ``report.md`` there puts the runs side by side
(:mod:`benchmarks.scale_compare`).

Outputs of one run in ``--out``: ``resources.csv``, ``api_requests.csv``,
``task_delivery.csv``, ``relay_rtt.csv``, ``reaction_trials.csv``,
``login_flood.csv``, ``flood_api_requests.csv``, ``summary.json`` and ``report.md``.
No timing is asserted anywhere; ``--quick`` is the smoke test the suite runs
(tests/benchmarks/test_scale_quick.py, in both topologies).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import dataclasses
import http.client
import json
import logging
import math
import os
import platform
import random
import re
import signal
import ssl
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Final

import msgspec
from websockets.exceptions import ConnectionClosed, InvalidHandshake

from agents.protocol import ProtocolError, ReplayGuard, VehicleTask, load_public_key
from agents.protocol.messages import (
    CommandSpec,
    EndTask,
    Event,
    Heartbeat,
    Position,
    Profile,
    Revoke,
    Task,
    TaskAccepted,
    TaskRefused,
)
from agents.uplink import Uplink
from benchmarks.nginx_proxy import raise_open_files_limit
from benchmarks.scale_compare import compare_md
from benchmarks.scale_platform import (
    ROOT,
    SERVERS,
    Child,
    PlatformQueries,
    PlatformTree,
    database_create,
    free_port,
    open_log,
    worktree,
)
from benchmarks.scale_probe import CAR_SERVICE, HOME, LIGHT_SERVICE
from benchmarks.scale_topology import (
    AGENTS_NET,
    API_NET,
    FLOOD_NET,
    TOPOLOGIES,
    Shape,
    ca_file,
    loopback_address,
    proxy_reroute,
    topology_start,
)

__all__ = ["MODES", "Params", "free_port", "main", "run"]

DEFAULT_DATABASE_URL = "postgres://postgres@127.0.0.1:5432/iouv_bench_scale"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/4"
#: What ``--phases`` may ask for: phase 1; phases 1 to 3 (one process); all four.
PHASES = ("heartbeats", "one", "all")
MODES = ("direct_silent", "direct_closed", "relay_silent", "relay_closed")
CLK_TCK = os.sysconf("SC_CLK_TCK")
#: A relayed command whose ack takes longer than this is counted as lost.
LOST_AFTER_S = 30.0


@dataclass(frozen=True)
class Params:
    """What one run does; :meth:`quick_mode` is the smoke test's small version."""

    agents: int = 1000
    agent_workers: int = 2  # processes running the light agents
    ramp_per_s: float = 50.0  # new uplinks per second, all workers together
    settle_s: float = 5.0  # quiet time before a measurement window
    window_s: float = 15.0  # CPU and memory window
    # Each API request runs on its own thread in the server; a platform without the
    # connection pool (a --baseline tree) leaves a connection open per such thread for
    # DB_CONN_MAX_AGE: more clients would take this shared PostgreSQL server's last
    # connections from other people.
    api_clients: int = 8
    # 0: each client requests its next session as soon as the last one ended (a closed
    # loop: the platform's most, with latency that is mostly waiting in line). Else the
    # clients together start this many sessions a second, evenly spaced (a paced load:
    # the latency a user meets at that rate).
    api_rate: float = 0.0
    api_duration_s: float = 20.0
    trials: int = 20  # per link-loss mode and topology
    trial_budget_s: float = 120.0  # per mode: an overloaded platform gets fewer trials
    link_loss_timeout_ms: int = 500
    relay_hz: float = 10.0
    cars: int = 2
    drain_s: float = 2.5  # after the API load, for the last acceptances to arrive
    start_delay_s: float = 2.0  # for the API worker and the relayed session to be ready
    server: str = SERVERS[0]  # the ASGI server the platform runs under
    phases: str = "all"  # one of PHASES
    # The platform's processes (benchmarks.scale_topology): "single" or "production",
    # and the production shape's sizes (2 cores: 2 gunicorn workers, 2 uvicorn).
    topology: str = "single"
    web: int = 1  # gunicorn instances (iouv-web@)
    web_workers: int = 2  # worker processes each (IOUV_WEB_WORKERS)
    web_threads: int = 4  # threads each (IOUV_WEB_THREADS)
    ws: int = 2  # uvicorn processes (iouv-ws@)
    # The login flood (0 clients: no flood phase): clients posting wrong passwords to
    # the portal's login as fast as they are answered, each from its own address, while
    # the API clients measure; flood_duration_s for the window without and the one with.
    flood_clients: int = 4
    flood_duration_s: float = 20.0
    # After the API phases, the fleet grown to this many light agents and measured
    # (the heartbeat phase at scale); 0 or not above ``agents``: no such phase.
    fleet_agents: int = 0
    quick: bool = False

    def __post_init__(self) -> None:
        if self.server not in SERVERS:
            raise ValueError(f"server must be one of {SERVERS}, not {self.server!r}")
        if self.phases not in PHASES:
            raise ValueError(f"phases must be one of {PHASES}, not {self.phases!r}")
        self.shape()  # raises ValueError for a topology it cannot run

    def shape(self) -> Shape:
        """The platform's processes, as :mod:`benchmarks.scale_topology` starts them."""
        return Shape(
            topology=self.topology,
            server=self.server,
            web=self.web,
            web_workers=self.web_workers,
            web_threads=self.web_threads,
            ws=self.ws,
        )

    @property
    def light_agents(self) -> int:
        """Light vehicles registered: the fleet phase's, if it grows the fleet."""
        return max(self.agents, self.fleet_agents)

    @property
    def two_processes(self) -> bool:
        """Whether phase 4 (one process against two, single topology) runs."""
        return self.phases == "all" and self.topology == "single"

    @property
    def cars_needed(self) -> int:
        """Cars registered and run: none when only the heartbeat phase runs."""
        return 0 if self.phases == "heartbeats" else self.cars

    def stages(self) -> list[int]:
        """Agent counts measured on the way up: a quarter, a half and all of them (only
        all of them below 200), so the cost per agent shows before any saturation."""
        if self.agents < 200:
            return [self.agents]
        return sorted({self.agents // 4, self.agents // 2, self.agents})

    @classmethod
    def quick_mode(cls, agents: int = 50) -> Params:
        return cls(
            agents=agents,
            agent_workers=1,
            ramp_per_s=500.0,
            settle_s=0.5,
            window_s=1.5,
            api_clients=3,
            api_duration_s=2.5,
            trials=2,
            link_loss_timeout_ms=300,
            drain_s=0.5,
            start_delay_s=1.0,
            trial_budget_s=60.0,
            flood_clients=2,
            flood_duration_s=2.0,
            fleet_agents=agents + 10,
            quick=True,
        )


# ======================================================================================
# Measuring processes and the machine
# ======================================================================================


def proc_cpu_s(pid: int) -> float:
    """CPU seconds (user + system, all threads) the process has used so far."""
    with open(f"/proc/{pid}/stat") as f:
        data = f.read()
    # The command name may contain spaces and parentheses: split after the last ")".
    fields = data[data.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread of the process (thread id -> seconds)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError), open(f"/proc/{pid}/task/{tid}/stat") as f:
            data = f.read()
            fields = data[data.rindex(")") + 2 :].split()
            out[tid] = (int(fields[11]) + int(fields[12])) / CLK_TCK
    return out


def proc_rss_kb(pid: int) -> int:
    """Resident memory of the process (VmRSS), in KiB."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def machine_busy_ticks() -> tuple[int, int]:
    """(busy, total) CPU ticks of the whole machine since boot, from /proc/stat."""
    with open("/proc/stat") as f:
        values = [int(v) for v in f.readline().split()[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0)
    total = sum(values[:8])
    return total - idle, total


def pids_named(name: str) -> list[int]:
    """Pids of every process whose command name is ``name`` (e.g. the PostgreSQL
    server's backends), visible to this user; empty if none."""
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError), open(f"/proc/{entry}/comm") as f:
            if f.read().strip() == name:
                out.append(int(entry))
    return out


#: What a window measures under one label: pids, a command name (``"postgres"``: every
#: process of that name), or a function giving the pids now (a gunicorn's workers).
Pids = list[int] | str | Callable[[], list[int]]


@dataclass
class Usage:
    """One process (or group of processes) over one window."""

    phase: str
    topology: str
    process: str
    window_s: float
    cpu_pct: float  # percent of one core
    rss_mb: float
    threads: str = ""  # platform processes: their busiest threads' CPU, "46 % + 29 % (2)"


class Window:
    """CPU use of named processes between :meth:`start` and :meth:`stop`; RSS at stop.

    A name may stand for several pids (the agent workers), for a command name
    (``"postgres"``) or for a function giving pids: those are looked up at :meth:`start`
    and again at :meth:`stop`,
    because the server starts a backend for each new connection while the window runs,
    and a backend born meanwhile is counted from its birth. A process that exits during
    the window is not counted.
    """

    def __init__(self, pids: dict[str, Pids]) -> None:
        self._named = {k: v for k, v in pids.items() if isinstance(v, str)}
        self._found = {k: v for k, v in pids.items() if callable(v)}
        self.pids: dict[str, list[int]] = {
            k: (v if isinstance(v, list) else []) for k, v in pids.items()
        }
        self._cpu0: dict[int, float] = {}
        self._threads0: dict[int, dict[str, float]] = {}
        self._t0 = 0.0
        self._machine0 = (0, 0)

    def _lookup(self) -> None:
        for label, comm in self._named.items():
            self.pids[label] = sorted(set(self.pids[label]) | set(pids_named(comm)))
        for label, find in self._found.items():
            self.pids[label] = sorted(set(self.pids[label]) | set(find()))

    def start(self) -> None:
        self._lookup()
        self._t0 = time.monotonic()
        self._machine0 = machine_busy_ticks()
        for pids in self.pids.values():
            for pid in pids:
                with contextlib.suppress(OSError):
                    self._cpu0[pid] = proc_cpu_s(pid)
        for name, pids in self.pids.items():
            if name.startswith("platform"):
                for pid in pids:
                    with contextlib.suppress(OSError):
                        self._threads0[pid] = thread_cpu_s(pid)

    def stop(self, *, phase: str, topology: str) -> list[Usage]:
        elapsed = time.monotonic() - self._t0
        busy1, total1 = machine_busy_ticks()
        self._lookup()
        busy0, total0 = self._machine0
        out = []
        for name, pids in self.pids.items():
            cpu = rss = 0.0
            for pid in pids:
                with contextlib.suppress(OSError):
                    cpu += proc_cpu_s(pid) - self._cpu0.get(pid, 0.0)
                    rss += proc_rss_kb(pid)
            threads = ""
            if name.startswith("platform") and len(pids) == 1 and pids[0] in self._threads0:
                with contextlib.suppress(OSError):
                    now, then = thread_cpu_s(pids[0]), self._threads0[pids[0]]
                    busy = sorted(
                        (100 * (v - then.get(tid, 0.0)) / elapsed for tid, v in now.items()),
                        reverse=True,
                    )
                    threads = " + ".join(f"{b:.0f} %" for b in busy[:3]) + f" ({len(now)})"
            out.append(
                Usage(phase, topology, name, elapsed, 100 * cpu / elapsed, rss / 1024, threads)
            )
        cores = os.cpu_count() or 1
        machine = 100 * cores * (busy1 - busy0) / max(1, total1 - total0)
        out.append(Usage(phase, topology, "whole machine", elapsed, machine, 0.0))
        return out


def machine_info() -> dict[str, Any]:
    """The machine the run is on: CPU model, cores, RAM, OS, Python, date."""
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    ram_gb = 0.0
    with contextlib.suppress(OSError), open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemTotal:"):
                ram_gb = int(line.split()[1]) / 1024 / 1024
    return {
        "cpu_model": model,
        "cores": os.cpu_count(),
        "ram_gb": round(ram_gb, 1),
        "os": platform.platform(),
        "python": platform.python_version(),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "load_average_at_start": [round(v, 2) for v in os.getloadavg()],
        "open_files_limit": raise_open_files_limit(),
    }


def summary(values: Iterable[float]) -> dict[str, float]:
    """n, min, p50, p95, max and mean (nearest-rank percentiles); zeros when empty."""
    ordered = sorted(values)
    if not ordered:
        return {"n": 0, "min": 0.0, "p50": 0.0, "p95": 0.0, "max": 0.0, "mean": 0.0}

    def rank(q: float) -> float:
        return ordered[max(0, math.ceil(q * len(ordered)) - 1)]

    return {
        "n": len(ordered),
        "min": ordered[0],
        "p50": rank(0.50),
        "p95": rank(0.95),
        "max": ordered[-1],
        "mean": statistics.fmean(ordered),
    }


# ======================================================================================
# The world in the database (written by the platform's tree: benchmarks.scale_probe)
# ======================================================================================


@dataclass
class AgentSpec:
    """One registered vehicle and what its agent needs to connect."""

    vehicle_id: str
    credential: str
    name: str
    lat: float
    lon: float


@dataclass
class World:
    """Everything the load needs, as plain data (it travels to worker processes)."""

    public_key: str
    light: list[AgentSpec]
    cars: list[AgentSpec]
    client_tokens: list[str]
    driver_token: str

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> World:
        """The world ``scale_probe.world_build`` returned."""
        return cls(
            public_key=data["public_key"],
            light=[AgentSpec(**a) for a in data["light"]],
            cars=[AgentSpec(**a) for a in data["cars"]],
            client_tokens=list(data["client_tokens"]),
            driver_token=data["driver_token"],
        )


# ======================================================================================
# Child processes: the workers (the platform's and nginx: benchmarks.scale_topology)
# ======================================================================================


@dataclass
class WorkerState:
    """What an agent worker last reported."""

    connected: int = 0
    registrations: int = 0
    tasks: dict[str, float] = field(default_factory=dict)  # session id -> wall time
    heartbeats: int = 0  # sent since the worker started
    at: float = 0.0  # when it reported (time.monotonic(), one clock for the machine)


class AgentWorkers:
    """The ``--agent-worker`` processes running the light agents."""

    def __init__(self) -> None:
        self.children: list[Child] = []
        self.states: list[WorkerState] = []
        self._readers: list[asyncio.Task[None]] = []

    async def start(
        self,
        *,
        specs: list[AgentSpec],
        world: World,
        url: str,
        workers: int,
        ramp_per_s: float,
        env: dict[str, str],
        logs: Path,
    ) -> None:
        """Start ``workers`` more processes sharing ``specs``, opening their uplinks at
        ``ramp_per_s`` per second together."""
        n = max(1, workers)
        # Each agent leaves from an address of its own, as a fleet does: nginx limits
        # connections per address (deploy/nginx/iouv.conf).
        where = {s.vehicle_id: i for i, s in enumerate(world.light)}
        for offset in range(n):
            mine = specs[offset::n]
            index = len(self.children)
            spec_path = logs / f"agent-worker-{index}.json"
            spec_path.write_text(
                json.dumps(
                    {
                        "url": url,
                        "public_key": world.public_key,
                        "agents": [
                            {
                                **asdict(s),
                                "address": loopback_address(AGENTS_NET, where[s.vehicle_id]),
                            }
                            for s in mine
                        ],
                        "ramp_per_s": ramp_per_s / n,
                    }
                )
            )
            with open_log(logs / f"agent-worker-{index}.log") as log_file:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    "benchmarks.scale",
                    "--agent-worker",
                    str(spec_path),
                    cwd=ROOT,
                    env=env,
                    stdout=asyncio.subprocess.PIPE,
                    stderr=log_file,
                    limit=1 << 24,
                )
            state = WorkerState()
            self.children.append(Child(f"agent worker {index}", proc))
            self.states.append(state)
            self._readers.append(asyncio.create_task(self._read(proc, state)))

    @staticmethod
    async def _read(proc: asyncio.subprocess.Process, state: WorkerState) -> None:
        assert proc.stdout is not None
        async for line in proc.stdout:
            with contextlib.suppress(ValueError):
                report = json.loads(line)
                state.connected = report["connected"]
                state.registrations = report["registrations"]
                state.tasks.update({sid: t for sid, t in report["tasks"]})
                state.heartbeats = report["heartbeats"]
                state.at = report["at"]

    @property
    def connected(self) -> int:
        return sum(s.connected for s in self.states)

    @property
    def registrations(self) -> int:
        return sum(s.registrations for s in self.states)

    def heartbeat_marks(self) -> list[tuple[int, float]]:
        """Each worker's last report: (heartbeats sent so far, when it reported)."""
        return [(s.heartbeats, s.at) for s in self.states]

    @staticmethod
    def heartbeat_rate(before: list[tuple[int, float]], after: list[tuple[int, float]]) -> float:
        """Heartbeats sent per second between two :meth:`heartbeat_marks`, all workers
        together. Each worker's rate is taken between its own reports (one a second),
        not the caller's instants, so a short window is not off by a report's worth."""
        rate = 0.0
        for (n0, t0), (n1, t1) in zip(before, after, strict=False):
            if t1 > t0:
                rate += (n1 - n0) / (t1 - t0)
        return rate

    def task_times(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for state in self.states:
            out.update(state.tasks)
        return out

    async def stop(self) -> None:
        for child in self.children:
            await child.stop()
        for reader in self._readers:
            reader.cancel()


# ======================================================================================
# The light agent (worker processes; no Django here)
# ======================================================================================

LIGHT_COMMANDS = [{"name": "stop", "args": {}, "description": "Stop where you are"}]


class LightAgent:
    """A vehicle agent without a vehicle: the real uplink, tasks verified and accepted,
    ``task_ended`` on ``end_task``/``revoke``. Heartbeats say ``in_service`` while a
    task runs, like the real agent."""

    def __init__(
        self, spec: dict[str, Any], *, url: str, public_key: Any, tasks: list[Any]
    ) -> None:
        self.vehicle_id = spec["vehicle_id"]
        self.position = Position(lat=spec["lat"], lon=spec["lon"])
        self.public_key = public_key
        self.session: str | None = None
        self.tasks = tasks
        self.heartbeats = 0  # built for sending: the uplink sends each one at once
        self.guard = ReplayGuard(max_entries=1000)
        self.uplink = Uplink(
            url=url.rstrip("/") + "/ws/agent/",
            vehicle_id=self.vehicle_id,
            credential=spec["credential"],
            on_message=self.on_message,
            profile=self.profile,
            heartbeat=self.heartbeat,
            reconnect_min_s=0.5,
            reconnect_max_s=5.0,
            connect_options={"local_addr": (spec["address"], 0)} if spec.get("address") else None,
        )

    def profile(self) -> Profile:
        return Profile(
            vehicle_type="drone",
            adapter="light",
            attributes={},
            commands=msgspec.convert(LIGHT_COMMANDS, list[CommandSpec]),
            telemetry=[],
            control_url="",
            video=False,
            position=self.position,
            battery=90.0,
        )

    def heartbeat(self) -> Heartbeat:
        self.heartbeats += 1
        return Heartbeat(
            seq=0,
            position=self.position,
            battery=90.0,
            status="in_service" if self.session else "idle",
        )

    async def on_message(self, msg: Any) -> None:
        if isinstance(msg, Task):
            try:
                task = VehicleTask.verify(
                    msg.token,
                    self.public_key,
                    vehicle_id=self.vehicle_id,
                    replay_guard=self.guard,
                )
            except ProtocolError as exc:
                self.uplink.send(TaskRefused(code=exc.code, reason=str(exc)))
                return
            self.tasks.append((task.session_id, time.time()))
            self.session = task.session_id
            self.uplink.send(TaskAccepted(session_id=task.session_id))
        elif isinstance(msg, EndTask | Revoke) and msg.session_id == self.session:
            self.session = None
            self.uplink.send(
                Event(
                    session_id=msg.session_id,
                    event="task_ended",
                    data={"reason": msg.reason},
                )
            )


async def agent_worker(spec: dict[str, Any]) -> None:
    """Run the light agents of a worker spec; print a JSON status line every second
    (connected uplinks, registrations so far, tasks received since the last line)."""
    raise_open_files_limit()
    key = load_public_key(spec["public_key"])
    tasks: list[Any] = []
    agents = [LightAgent(a, url=spec["url"], public_key=key, tasks=tasks) for a in spec["agents"]]
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    async def report() -> None:
        while True:
            sent = tasks[:]
            del tasks[: len(sent)]
            line = {
                "connected": sum(a.uplink.connected.is_set() for a in agents),
                "registrations": sum(a.uplink.connections for a in agents),
                "tasks": sent,
                "heartbeats": sum(a.heartbeats for a in agents),
                "at": time.monotonic(),
            }
            sys.stdout.write(json.dumps(line) + "\n")
            sys.stdout.flush()
            await asyncio.sleep(1.0)

    runs = [asyncio.create_task(report())]
    interval = 1.0 / max(1.0, float(spec["ramp_per_s"]))
    for agent in agents:
        if stop.is_set():
            break
        runs.append(asyncio.create_task(agent.uplink.run()))
        await asyncio.sleep(interval)
    await stop.wait()
    # Exit without closing handshakes: a thousand of them would only slow the next phase,
    # and the kernel closes every socket anyway.
    sys.stdout.flush()
    os._exit(0)


# ======================================================================================
# API load (worker process)
# ======================================================================================


class ApiClient:
    """A keep-alive HTTP/1.1 client for the JSON API, one per thread: ``base`` is
    ``http://`` or ``https://`` (the CA trusted through ``SSL_CERT_FILE``), ``source``
    the local address it connects from (empty: the system's choice)."""

    def __init__(self, base: str, token: str, *, source: str = "") -> None:
        self.https = base.startswith("https://")
        host, _, port = base.partition("://")[2].partition(":")
        self.host, self.port, self.token = host, int(port or (443 if self.https else 80)), token
        self.source = source
        self.conn: http.client.HTTPConnection | None = None

    def connect(self) -> http.client.HTTPConnection:
        """A new connection to ``base`` (not opened until its first request)."""
        source = (self.source, 0) if self.source else None
        if self.https:
            return http.client.HTTPSConnection(
                self.host,
                self.port,
                timeout=60,
                source_address=source,
                context=ssl.create_default_context(),
            )
        return http.client.HTTPConnection(self.host, self.port, timeout=60, source_address=source)

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> tuple[int, Any]:
        """(status, parsed JSON body); status 0 when the connection failed, body None
        when the response was not JSON (a proxy's error page)."""
        payload = json.dumps(body or {}).encode()
        headers = {
            "Authorization": f"Bearer {self.token}",
            "Content-Type": "application/json",
            "Connection": "keep-alive",
        }
        for attempt in (0, 1):
            if self.conn is None:
                self.conn = self.connect()
            try:
                self.conn.request(
                    method, path, body=None if method == "GET" else payload, headers=headers
                )
                response = self.conn.getresponse()
                raw = response.read()
                if response.getheader("Connection", "").lower() == "close":
                    self.conn.close()
                    self.conn = None
            except (OSError, http.client.HTTPException):
                if self.conn is not None:
                    self.conn.close()
                self.conn = None
                if attempt:
                    return 0, None
                continue
            try:
                return response.status, json.loads(raw) if raw else None
            except ValueError:
                # nginx's own 502 page when no upstream answered: the status says so.
                return response.status, None
        return 0, None


def _start_awaited() -> float:
    """A load worker's half of :func:`_load_go`: say it is ready (imports done, spec
    read) on stdout, then read when its clients start (Unix time) from stdin."""
    print(json.dumps({"ready": True}), flush=True)
    return float(json.loads(sys.stdin.readline())["start_wall"])


def api_worker(spec_path: str) -> None:
    """API clients: each thread requests a session of the light service for a random
    target, then ends it, until the duration is over; at once again (closed loop), or,
    with the spec's ``rate``, at its next turn of an even pace shared by the clients.
    With the spec's ``services``, each turn first reads the catalogue (``GET
    /api/v1/services``); ``sources``: each client's own address. Writes one CSV row per
    request to the spec's ``out``."""
    with open(spec_path) as f:
        spec = json.load(f)
    from agents.geo import offset

    spec["start_wall"] = _start_awaited()
    deadline_wall = spec["start_wall"] + spec["duration_s"]
    rate, clients = float(spec.get("rate") or 0.0), len(spec["tokens"])
    rows: list[tuple[Any, ...]] = []
    lock = threading.Lock()

    def client(index: int, token: str) -> None:
        rng = random.Random(index)
        sources = spec.get("sources") or []
        api = ApiClient(spec["base"], token, source=sources[index] if sources else "")
        mine: list[tuple[Any, ...]] = []
        # Every client starts at the same instant, when the parent's window opens.
        time.sleep(max(0.0, spec["start_wall"] - time.time()))
        turn = 0
        while True:
            if rate:
                # Paced: session turn * clients + index of the whole load is due then; a
                # client still busy with its last one starts late (fewer sessions/s).
                due = spec["start_wall"] + (turn * clients + index) / rate
                turn += 1
                if due >= deadline_wall:
                    break
                time.sleep(max(0.0, due - time.time()))
            elif time.time() >= deadline_wall:
                break
            if spec.get("services"):
                started = time.time()
                t0 = time.perf_counter()
                status, _ = api.call("GET", "/api/v1/services")
                ms = (time.perf_counter() - t0) * 1000
                mine.append((index, "services", started, ms, status, ""))
            distance, bearing = 1000 * math.sqrt(rng.random()), rng.uniform(0, 2 * math.pi)
            lat, lon = offset(HOME, distance * math.cos(bearing), distance * math.sin(bearing))
            started = time.time()
            t0 = time.perf_counter()
            status, body = api.call(
                "POST",
                "/api/v1/sessions",
                {"service": spec["service"], "target": {"lat": lat, "lon": lon}},
            )
            ms = (time.perf_counter() - t0) * 1000
            sid = ""
            if status == 201:
                sid = body["session"]["id"]
            elif isinstance(body, dict) and "error" in body:
                sid = body["error"].get("session_id", "")
            mine.append((index, "request", started, ms, status, sid))
            if status != 201:
                time.sleep(0.05)
                continue
            started = time.time()
            t0 = time.perf_counter()
            status, _ = api.call("POST", f"/api/v1/sessions/{sid}/end", {})
            mine.append((index, "end", started, (time.perf_counter() - t0) * 1000, status, sid))
        with lock:
            rows.extend(mine)

    threads = [
        threading.Thread(target=client, args=(i, token), daemon=True)
        for i, token in enumerate(spec["tokens"])
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    with open(spec["out"], "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["client", "endpoint", "start_wall", "latency_ms", "status", "session_id"])
        writer.writerows(rows)
    print(json.dumps({"requests": len(rows)}), flush=True)


#: The form's fields Django's CSRF check needs, from the login page.
_CSRF_INPUT = re.compile(rb'name="csrfmiddlewaretoken" value="([^"]+)"')


def flood_worker(spec_path: str) -> None:
    """Login flood: each of the spec's ``sources`` (one thread each, from that address)
    reads the portal's login page once beforehand (its CSRF cookie and token, as a
    script would), then posts a wrong password for ``flood-<client>`` again and again,
    each as soon as the last is answered, from ``start_wall`` for ``duration_s`` (at
    least once). Writes one CSV row per
    attempt to the spec's ``out``: status, and who answered a 429 (``nginx``'s
    limit_req page, else the platform's lockout)."""
    with open(spec_path) as f:
        spec = json.load(f)
    spec["start_wall"] = _start_awaited()
    deadline = spec["start_wall"] + spec["duration_s"]
    rows: list[tuple[Any, ...]] = []
    lock = threading.Lock()
    path = "/accounts/login/"
    origin = spec["base"]

    def login_form(api: ApiClient) -> tuple[str, str]:
        """The CSRF cookie and the form's token, read from the login page; empty when
        the page could not be read."""
        try:
            conn = api.conn = api.conn or api.connect()
            conn.request("GET", path, headers={"Connection": "keep-alive"})
            response = conn.getresponse()
            found = _CSRF_INPUT.search(response.read())
        except (OSError, http.client.HTTPException):
            if api.conn is not None:
                api.conn.close()
            api.conn = None
            return "", ""
        cookie = ""
        for header in response.msg.get_all("Set-Cookie") or []:
            if header.startswith("csrftoken="):
                cookie = header.split(";", 1)[0]
        return cookie, found.group(1).decode() if found else ""

    def client(index: int, source: str) -> None:
        api = ApiClient(spec["base"], "", source=source)
        mine: list[tuple[Any, ...]] = []
        # The form first, before the flood starts (as a script prepares its attack);
        # then attempts until the deadline, at least one each.
        cookie, token = login_form(api)
        while not token and time.time() < deadline:
            time.sleep(0.5)
            cookie, token = login_form(api)
        time.sleep(max(0.0, spec["start_wall"] - time.time()))
        while token:
            conn = api.conn = api.conn or api.connect()
            started = time.time()
            t0 = time.perf_counter()
            form = f"username=flood-{index}&password=wrong-{random.random()}"
            form += f"&csrfmiddlewaretoken={token}"
            try:
                conn.request(
                    "POST",
                    path,
                    body=form.encode(),
                    headers={
                        "Content-Type": "application/x-www-form-urlencoded",
                        "Cookie": cookie,
                        "Origin": origin,
                        "Referer": origin + path,
                        "Connection": "keep-alive",
                    },
                )
                response = conn.getresponse()
                body = response.read()
                ms = (time.perf_counter() - t0) * 1000
                who = ""
                if response.status == 429:
                    who = "nginx" if b"<center>nginx" in body else "platform"
                mine.append((index, started, ms, response.status, who))
                if response.getheader("Connection", "").lower() == "close":
                    conn.close()
                    api.conn = None
            except (OSError, http.client.HTTPException):
                ms = (time.perf_counter() - t0) * 1000
                mine.append((index, started, ms, 0, "connection failed"))
                conn.close()
                api.conn = None
                time.sleep(0.05)
            if time.time() >= deadline:
                break
        with lock:
            rows.extend(mine)

    threads = [
        threading.Thread(target=client, args=(i, source), daemon=True)
        for i, source in enumerate(spec["sources"])
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    with open(spec["out"], "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["client", "start_wall", "latency_ms", "status", "answered_by"])
        writer.writerows(rows)
    print(json.dumps({"attempts": len(rows)}), flush=True)


def _api_load(p: Params) -> str:
    """How the API load was driven, for the report."""
    if p.api_rate:
        return (
            f"{p.api_clients} API clients starting {p.api_rate:g} sessions/s together, evenly paced"
        )
    return f"{p.api_clients} API clients in a closed loop"


# ======================================================================================
# Cars, controllers and the relay (this process)
# ======================================================================================


class Probe:
    """Timestamps, on the agent's side, what a link-loss trial needs: when a control
    frame last arrived, when the hub saw the controller's link close, and when the
    adapter was told to perform its safe action. All ``time.monotonic()``, the clock
    the controller in this process uses too."""

    def __init__(self, agent: Any) -> None:
        self.agent = agent
        self.last_rx = 0.0
        self.lost_at = 0.0
        self.safe_at = 0.0
        self.fired = asyncio.Event()
        hub, adapter = agent.hub, agent.adapter
        received, disconnected, safe_action = hub.received, hub.disconnected, adapter.safe_action

        async def timed_received(link: Any, raw: Any) -> None:
            self.last_rx = time.monotonic()
            await received(link, raw)

        async def timed_disconnected(link: Any) -> None:
            self.lost_at = time.monotonic()
            await disconnected(link)

        async def timed_safe_action(action: str) -> None:
            if not self.fired.is_set():
                self.safe_at = time.monotonic()
                self.fired.set()
            await safe_action(action)

        # Instance attributes shadow the methods: the hub and the control server look
        # them up on every call, so the wrappers see exactly what the agent does.
        hub.received = timed_received
        hub.disconnected = timed_disconnected
        adapter.safe_action = timed_safe_action

    def arm(self) -> None:
        """Forget the last trial: the next safe action is this trial's."""
        self.fired.clear()
        self.lost_at = 0.0


async def cars_start(
    stack: contextlib.AsyncExitStack, *, world: World, url: str
) -> dict[str, Probe]:
    """Run the cars' full agents (car adapter on mock pins) in this process; they are
    cancelled when ``stack`` closes. Returns a probe per vehicle id."""
    from agents.config import AgentConfig, ControlConfig
    from agents.runtime import Agent
    from agents.simulation import simulator_running

    probes = {}
    for spec in world.cars:
        config = AgentConfig(
            platform_url=url,
            vehicle_id=spec.vehicle_id,
            credential=spec.credential,
            platform_public_key=world.public_key,
            adapter="car",
            adapter_options={"origin": [spec.lat, spec.lon]},
            control=ControlConfig(host="127.0.0.1", port=0),
            name=spec.name,
            reconnect_max_s=5.0,
        )
        # The car on its simulator (mock pins, a world), stopped after its agent.
        simulation = await stack.enter_async_context(
            simulator_running(config.adapter, config.adapter_options)
        )
        agent = Agent(dataclasses.replace(config, adapter_options=simulation.options))
        task = asyncio.create_task(agent.run())

        async def cancel(task: asyncio.Task[None] = task) -> None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

        stack.push_async_callback(cancel)
        await asyncio.wait_for(agent.ready.wait(), 30)
        probes[spec.vehicle_id] = Probe(agent)
    return probes


class ApiRefused(RuntimeError):
    """An API call answered with something else than 2xx."""

    def __init__(self, status: int, data: Any, what: str) -> None:
        super().__init__(f"{what}: {status} {data}")
        self.status = status
        error = data.get("error") if isinstance(data, dict) else None
        self.message = str(error.get("message", "")) if isinstance(error, dict) else str(data)


async def api(
    base: str, token: str, method: str, path: str, body: dict[str, Any] | None = None
) -> Any:
    """One API call from this process; raises ApiRefused on anything but 2xx."""

    def call() -> tuple[int, Any]:
        return ApiClient(base, token).call(method, path, body)

    status, data = await asyncio.to_thread(call)
    if not 200 <= status < 300:
        raise ApiRefused(status, data, f"{method} {path}")
    return data


async def car_session(
    *, base: str, token: str, relay: bool, results: Results, what: str
) -> dict[str, Any]:
    """Request a session of the car service, retrying for up to a minute while no car
    counts as online and idle (an overloaded platform may store a car's heartbeats too
    late for assignment); each retry is noted in the results."""
    deadline = time.monotonic() + 60
    while True:
        try:
            return dict(
                await api(
                    base,
                    token,
                    "POST",
                    "/api/v1/sessions",
                    {"service": CAR_SERVICE, "relay": relay, "target": _home()},
                )
            )
        except ApiRefused as exc:
            if exc.status != 422 or time.monotonic() > deadline:
                raise
            results.notes.append(f"{what}: no car available yet, retried ({exc.message})")
            await asyncio.sleep(1.0)


def _home() -> dict[str, float]:
    return {"lat": HOME[0], "lon": HOME[1]}


async def task_arrived(probe: Probe, session_id: str) -> None:
    """Wait until the car runs ``session_id``'s task. The API answers with the grant as
    soon as the task is sent; a direct client that connects at once can beat the task to
    the agent and be refused (``no_task``), so it waits as a careful client would.
    Raises TimeoutError after 30 s."""
    hub = probe.agent.hub
    async with asyncio.timeout(30):
        # The hub offers no event for "task accepted": poll it.
        while hub.task is None or hub.task.session_id != session_id:  # noqa: ASYNC110
            await asyncio.sleep(0.01)


async def _recv(
    ws: Any, kind: str, *, seq: int | None = None, within: float = 10.0
) -> dict[str, Any]:
    """The next message of ``kind`` (an ``ack`` with ``seq``), answering the agent's
    pings on the way like a real client. Raises TimeoutError after ``within`` s."""
    deadline = time.monotonic() + within
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), max(0.01, deadline - time.monotonic())))
        if msg["type"] == "ping":
            await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))
        elif msg["type"] == kind and (seq is None or msg.get("seq") == seq):
            return dict(msg)
        elif msg["type"] == "error":
            raise RuntimeError(f"the agent refused: {msg}")


async def _controller(task: dict[str, Any]) -> Any:
    """Connect to the user task's control URL (the agent or the relay), authenticate,
    and return the socket once the agent's ``welcome`` says controller."""
    from websockets.asyncio.client import connect

    ws = await connect(task["control_url"], proxy=None, compression=None, open_timeout=15)
    try:
        await ws.send(json.dumps({"type": "auth", "grant": task["grant"]}))
        welcome = await _recv(ws, "welcome", within=15)
        if welcome["role"] != "controller":
            raise RuntimeError(f"not the controller: {welcome}")
    except BaseException:
        # A refused or failed attempt leaves: a socket kept open would hold a viewer's
        # place at the agent through the next attempts.
        await ws.close()
        raise
    return ws


@dataclass
class Trial:
    """One link-loss trial."""

    topology: str
    mode: str
    trial: int
    reaction_ms: float  # controller's last input (or its socket's death) -> safe action
    agent_ms: float  # agent's view: last frame received (or link seen closed) -> safe action
    platform_logged: bool = False


_TRIAL_ERRORS = (
    ApiRefused,
    RuntimeError,
    OSError,
    TimeoutError,
    ConnectionClosed,
    InvalidHandshake,
)


async def _one_trial(
    *, topology: str, mode: str, index: int, task: dict[str, Any], probe: Probe
) -> Trial | None:
    """Drive, then lose the link as ``mode`` says; the trial, or None when the car did
    not perform its safe action within 10 s. Connection failures raise."""
    closed = mode.endswith("closed")
    ws = await _controller(task)
    try:
        forward = {"type": "command", "seq": 1, "name": "forward", "args": {"speed": 0.5}}
        await ws.send(json.dumps(forward))
        await _recv(ws, "ack", seq=1)
        for _ in range(3):  # a user holding the key: input at a steady pace
            await asyncio.sleep(0.05)
            await ws.send(json.dumps({"type": "keepalive"}))
        probe.arm()
        last_input = time.monotonic()
        if closed:
            ws.transport.abort()
        try:
            await asyncio.wait_for(probe.fired.wait(), 10)
        except TimeoutError:
            return None
    finally:
        if not closed:
            await ws.close()
    # What the agent acted on: the close, if it read the close before acting; else the
    # silence since the last frame it read (on a saturated machine its link-loss timeout
    # can act before it reads the close). A frame read only after the action (it sat
    # unread meanwhile) leaves nothing later to measure from: 0.
    seen = probe.lost_at if closed and 0 < probe.lost_at <= probe.safe_at else probe.last_rx
    return Trial(
        topology,
        mode,
        index,
        (probe.safe_at - last_input) * 1000,
        max(0.0, probe.safe_at - seen) * 1000,
    )


@dataclass
class CarSession:
    """A car's session opened for the trials and the relayed control session."""

    session_id: str
    relay: bool
    probe: Probe


async def car_sessions_open(
    *, base: str, token: str, probes: dict[str, Probe], results: Results
) -> dict[bool, CarSession]:
    """One session per way of reaching a car (direct, relayed), each on its own car, and
    opened before the fleet connects: assignment needs the car counted online, and an
    overloaded platform stores the car's heartbeats too late for that. Grants for each
    connection come from the API later, as a reconnecting user gets them."""
    out = {}
    for relay in (False, True):
        created = await car_session(
            base=base, token=token, relay=relay, results=results, what="opening the car sessions"
        )
        probe = probes[created["task"]["vehicle_id"]]
        await task_arrived(probe, created["session"]["id"])
        out[relay] = CarSession(created["session"]["id"], relay, probe)
    return out


async def _grant(base: str, token: str, session: CarSession) -> dict[str, Any]:
    path = f"/api/v1/sessions/{session.session_id}/grant"
    return dict((await api(base, token, "POST", path))["task"])


async def reaction_trials(
    *,
    topology: str,
    modes: Sequence[str],
    n: int,
    base: str,
    token: str,
    sessions: dict[bool, CarSession],
    results: Results,
    budget_s: float,
    db: PlatformQueries,
) -> list[Trial]:
    """Link loss to safe action, ``n`` times per mode (at most ``budget_s`` seconds per
    mode), a fresh grant per trial as a reconnecting user gets.

    ``*_silent``: the controller drives, then sends nothing more (a pulled cable looks
    the same); the agent's watchdog fires after the task's link-loss timeout.
    ``*_closed``: the controller's socket is closed abruptly (the transport aborted, no
    WebSocket close handshake: what a crashed tab or browser process leaves).
    ``direct_*`` talk to the agent's control socket; ``relay_*`` go through the
    platform's relay, where a dead socket reaches the agent as ``relay_close``.
    """
    trials: list[Trial] = []
    for mode in modes:
        session = sessions[mode.startswith("relay")]
        first = len(trials)
        logged_before = await db.call("failsafes_logged", session_id=session.session_id)
        budget_end = time.monotonic() + budget_s
        for i in range(n):
            if time.monotonic() > budget_end:
                results.notes.append(
                    f"{topology}/{mode}: stopped after {i} of {n} trials, the "
                    f"{budget_s:g} s budget was spent (trials were slow to connect)"
                )
                break
            for _attempt in range(3):
                try:
                    task = await _grant(base, token, session)
                    trial = await _one_trial(
                        topology=topology, mode=mode, index=i, task=task, probe=session.probe
                    )
                except _TRIAL_ERRORS as exc:
                    # A user would reconnect: so does the trial, with a fresh grant.
                    results.notes.append(
                        f"{topology}/{mode}: a trial could not drive the car, retried "
                        f"({type(exc).__name__}: {str(exc)[:100]})"
                    )
                    await asyncio.sleep(1.0)
                    continue
                if trial is None:
                    results.notes.append(f"{topology}/{mode}: trial {i}: NO SAFE ACTION in 10 s")
                else:
                    trials.append(trial)
                break
            await asyncio.sleep(0.2)
        done = len(trials) - first
        deadline = time.monotonic() + 15
        count = await db.call("failsafes_logged", session_id=session.session_id) - logged_before
        while count < done and time.monotonic() < deadline:
            await asyncio.sleep(0.5)
            count = await db.call("failsafes_logged", session_id=session.session_id) - logged_before
        for trial in trials[first : first + count]:
            trial.platform_logged = True
    return trials


async def relay_session(
    *,
    base: str,
    token: str,
    session: CarSession,
    hz: float,
    ready: asyncio.Event,
    counting: asyncio.Event,
    until: asyncio.Event,
) -> tuple[list[float], int]:
    """A relayed controller: once connected (``ready`` is set), commands at ``hz``
    through the platform's relay, each waiting for its ack, until ``until`` is set.
    Returns the round trips (ms) of the commands acknowledged while ``counting`` was set
    (the load's window) and how many got no ack within LOST_AFTER_S (counted lost)."""
    rtts: list[float] = []
    lost = 0
    ws = await _controller(await _grant(base, token, session))
    try:
        ready.set()
        seq = 0
        next_at = time.monotonic()
        while not until.is_set():
            seq += 1
            name = "forward" if seq % 2 else "stop"
            args = {"speed": 0.3} if name == "forward" else {}
            start = time.monotonic()
            await ws.send(json.dumps({"type": "command", "seq": seq, "name": name, "args": args}))
            try:
                await _recv(ws, "ack", seq=seq, within=LOST_AFTER_S)
                # Counted when the ack lands in the window: on an overloaded platform one
                # round trip can outlast a short window, and must still show.
                if counting.is_set():
                    rtts.append((time.monotonic() - start) * 1000)
            except TimeoutError:
                lost += counting.is_set()
            next_at = max(next_at + 1 / hz, time.monotonic())
            await asyncio.sleep(next_at - time.monotonic())
    finally:
        await ws.close()
    return rtts, lost


# ======================================================================================
# The run
# ======================================================================================


@dataclass
class Results:
    """Everything measured, as the outputs need it."""

    params: Params
    machine: dict[str, Any]
    command: str
    database: str
    usage: list[Usage] = field(default_factory=list)
    fleet: dict[str, dict[str, Any]] = field(default_factory=dict)  # "topology/phase"
    online_after_s: dict[str, float | None] = field(default_factory=dict)
    api_rows: list[dict[str, Any]] = field(default_factory=list)
    deliveries: list[dict[str, Any]] = field(default_factory=list)
    sessions: dict[str, dict[str, int]] = field(default_factory=dict)
    relay: dict[str, tuple[list[float], int]] = field(default_factory=dict)
    trials: list[Trial] = field(default_factory=list)
    # The login flood: the API clients' requests ("topology" is the window: FLOOD_WINDOWS)
    # and the flood's attempts.
    flood_api_rows: list[dict[str, Any]] = field(default_factory=list)
    flood_attempts: list[dict[str, Any]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)  # phase -> seconds
    log_counts: dict[str, dict[str, int]] = field(default_factory=dict)  # process -> counts

    @contextlib.contextmanager
    def timed(self, phase: str) -> Iterator[None]:
        """Record how long the block took, for the report's run-time line."""
        start = time.monotonic()
        try:
            yield
        finally:
            self.timings[phase] = time.monotonic() - start


async def wait_online(
    *,
    names: Sequence[str],
    workers: AgentWorkers,
    expect_uplinks: int,
    within: float,
    db: PlatformQueries,
    registrations_at_least: int = 0,
) -> float | None:
    """Seconds until the workers report ``expect_uplinks`` connected uplinks (and at
    least ``registrations_at_least`` uplinks opened since they started) and the
    platform counts every vehicle of ``names`` online; None if that did not happen
    ``within`` seconds (the run goes on: how many were online is itself a result).

    After a restart, pass the registrations so far plus the agents: right after the
    cut, the workers' last report and the database (until ``IOUV_OFFLINE_AFTER_S``)
    still show the old uplinks online."""
    start = time.monotonic()
    while time.monotonic() - start < within:
        if workers.connected >= expect_uplinks and workers.registrations >= registrations_at_least:
            check = await db.call("fleet_check", names=list(names))
            if check["online"] == len(names):
                return time.monotonic() - start
        await asyncio.sleep(0.5)
    return None


async def measure(
    *,
    results: Results,
    topology: str,
    phase: str,
    pids: dict[str, Pids],
    seconds: float,
    names: Sequence[str],
    db: PlatformQueries,
    workers: AgentWorkers,
) -> None:
    """CPU and memory of ``pids`` over ``seconds``, the heartbeats the light agents sent
    meanwhile (per second), and the fleet as the platform sees it: online count
    (sampled every 2 s), heartbeat age at the end, vehicle rows updated per second."""
    before = await db.call("fleet_check", names=list(names))
    window = Window(pids)
    window.start()
    marks = workers.heartbeat_marks()
    end = time.monotonic() + seconds
    online = []
    while (remaining := end - time.monotonic()) > 0:
        await asyncio.sleep(min(2.0, remaining))
        if end - time.monotonic() > 0.5:
            online.append((await db.call("fleet_check", names=list(names)))["online"])
    usage = window.stop(phase=phase, topology=topology)
    heartbeats_per_s = workers.heartbeat_rate(marks, workers.heartbeat_marks())
    results.usage += usage
    after = await db.call("fleet_check", names=list(names), ages=True)
    online.append(after["online"])
    results.fleet[f"{topology}/{phase}"] = {
        **{k: v for k, v in after.items() if k != "ages"},
        "heartbeat_age_s": summary(after["ages"]),
        "online_min": min(online),
        "online_mean": statistics.fmean(online),
        "vehicle_updates_per_s": (after["vehicle_updates"] - before["vehicle_updates"])
        / usage[0].window_s,
        "heartbeats_per_s": heartbeats_per_s,
    }


def _read_api_rows(path: Path, topology: str, start_wall: float) -> list[dict[str, Any]]:
    with open(path, newline="") as f:
        return [
            {
                "topology": topology,
                "client": int(r["client"]),
                "endpoint": r["endpoint"],
                "start_s": float(r["start_wall"]) - start_wall,
                "latency_ms": float(r["latency_ms"]),
                "status": int(r["status"]),
                "session_id": r["session_id"],
            }
            for r in csv.DictReader(f)
        ]


async def load_phase(
    *,
    topology: str,
    results: Results,
    params: Params,
    world: World,
    base: str,
    env: dict[str, str],
    logs: Path,
    workers: AgentWorkers,
    pids: dict[str, Pids],
    names: Sequence[str],
    sessions: dict[bool, CarSession],
    db: PlatformQueries,
) -> None:
    """API clients + a relayed control session for ``api_duration_s``, measuring CPU."""
    out = logs / f"api-{topology}.csv"
    # The relayed session first: it is driving before the load starts, so its round trips
    # cover the whole window.
    ready, counting, done = asyncio.Event(), asyncio.Event(), asyncio.Event()
    relay = asyncio.create_task(
        relay_session(
            base=base,
            token=world.driver_token,
            session=sessions[True],
            hz=params.relay_hz,
            ready=ready,
            counting=counting,
            until=done,
        )
    )
    waiter = asyncio.ensure_future(ready.wait())
    await asyncio.wait([relay, waiter], timeout=90, return_when=asyncio.FIRST_COMPLETED)
    waiter.cancel()
    spec = logs / f"api-worker-{topology}.json"
    spec.write_text(
        json.dumps(
            {
                "base": base,
                "tokens": world.client_tokens,
                "service": LIGHT_SERVICE,
                "duration_s": params.api_duration_s,
                "rate": params.api_rate,
                "sources": _api_sources(world),
                "out": str(out),
            }
        )
    )
    proc = await _load_start("--api-worker", spec, env=env, log=logs / f"api-worker-{topology}.log")
    # Its clients begin together once it is ready (a busy machine takes seconds to start
    # a Python process).
    start_wall = await _load_go([proc], delay_s=params.start_delay_s)
    await asyncio.sleep(max(0.0, start_wall - time.time()))
    counting.set()
    await measure(
        results=results,
        topology=topology,
        phase="API load",
        pids={**pids, "API clients": [proc.pid]},
        seconds=params.api_duration_s,
        names=names,
        db=db,
        workers=workers,
    )
    done.set()
    await proc.communicate()
    try:
        results.relay[topology] = await relay
    except (*_TRIAL_ERRORS, ValueError) as exc:
        results.relay[topology] = ([], 0)
        results.notes.append(
            f"{topology}: the relayed control session failed "
            f"({type(exc).__name__}: {str(exc)[:160]})"
        )
    rows = await asyncio.to_thread(_read_api_rows, out, topology, start_wall)
    results.api_rows += rows
    created = [r for r in rows if r["endpoint"] == "request" and r["status"] == 201]
    # Give the last acceptances a moment to reach the workers' reports and the logs; a
    # busy platform logs them late, so wait (up to 15 s more) until they are all in.
    await asyncio.sleep(params.drain_s)
    ids = [r["session_id"] for r in created]
    deadline = time.monotonic() + 15
    check = await db.call("sessions_check", session_ids=ids)
    while check["task_accepted"] < check["task_deployed"] and time.monotonic() < deadline:
        await asyncio.sleep(1.0)
        check = await db.call("sessions_check", session_ids=ids)
    results.sessions[topology] = check
    arrived = workers.task_times()
    for r in created:
        at = arrived.get(r["session_id"])
        results.deliveries.append(
            {
                "topology": topology,
                "session_id": r["session_id"],
                "delivery_ms": (at - start_wall - r["start_s"]) * 1000 if at else None,
            }
        )


def _api_sources(world: World) -> list[str]:
    """Each API client's own address (nginx limits API requests per address)."""
    return [loopback_address(API_NET, i) for i in range(len(world.client_tokens))]


async def _load_start(
    flag: str, spec: Path, *, env: dict[str, str], log: Path
) -> asyncio.subprocess.Process:
    """A load process of this module (``--api-worker`` or ``--flood-worker`` on
    ``spec``), its errors to ``log``; :func:`_load_go` starts its clients, then the
    caller reads its output to its end."""
    with open_log(log) as log_file:
        return await asyncio.create_subprocess_exec(
            *(sys.executable, "-m", "benchmarks.scale", flag, str(spec)),
            cwd=ROOT,
            env=env,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=log_file,
        )


#: How long a load process may take to be ready (imports on a saturated machine).
LOAD_READY_S: Final = 120.0


async def _load_go(procs: Sequence[asyncio.subprocess.Process], *, delay_s: float) -> float:
    """Wait until every load process of :func:`_load_start` is ready, then tell them all
    to start their clients ``delay_s`` from now; returns that instant (Unix time). A
    window set before the processes started would pass by, on a busy machine, while
    they still import. RuntimeError if one exits or is not ready within LOAD_READY_S."""
    for proc in procs:
        assert proc.stdout is not None
        try:
            line = await asyncio.wait_for(proc.stdout.readline(), LOAD_READY_S)
        except TimeoutError:
            line = b""
        if not line.strip().startswith(b'{"ready"'):
            raise RuntimeError(f"a load process was not ready (it said {line[:200]!r})")
    start_wall = time.time() + delay_s
    for proc in procs:
        assert proc.stdin is not None
        proc.stdin.write(json.dumps({"start_wall": start_wall}).encode() + b"\n")
        await proc.stdin.drain()
        proc.stdin.close()
    return start_wall


def _read_flood_rows(path: Path, window: str, start_wall: float) -> list[dict[str, Any]]:
    with open(path, newline="") as f:
        return [
            {
                "window": window,
                "client": int(r["client"]),
                "start_s": float(r["start_wall"]) - start_wall,
                "latency_ms": float(r["latency_ms"]),
                "status": int(r["status"]),
                "answered_by": r["answered_by"],
            }
            for r in csv.DictReader(f)
        ]


#: The login flood's two windows: the API clients alone, then with the flood.
FLOOD_WINDOWS = ("without", "during")


async def flood_phase(
    *,
    results: Results,
    params: Params,
    world: World,
    base: str,
    env: dict[str, str],
    logs: Path,
    workers: AgentWorkers,
    pids: dict[str, Pids],
    names: Sequence[str],
    db: PlatformQueries,
) -> None:
    """The API clients as in phase 2, each turn also reading the catalogue (``GET
    /api/v1/services``), for ``flood_duration_s`` alone, then as long again while
    ``flood_clients`` clients, each from its own address, post wrong passwords to the
    portal's login as fast as they are answered (:func:`flood_worker`); CPU of every
    process in each window."""
    for window in FLOOD_WINDOWS:
        out = logs / f"flood-api-{window}.csv"
        spec = logs / f"flood-api-{window}.json"
        spec.write_text(
            json.dumps(
                {
                    "base": base,
                    "tokens": world.client_tokens,
                    "service": LIGHT_SERVICE,
                    "duration_s": params.flood_duration_s,
                    "rate": params.api_rate,
                    "sources": _api_sources(world),
                    "services": True,
                    "out": str(out),
                }
            )
        )
        procs = {
            "API clients": await _load_start(
                "--api-worker", spec, env=env, log=logs / f"flood-api-{window}.log"
            )
        }
        attempts = logs / "login-flood.csv"
        if window == "during":
            flood_spec = logs / "login-flood.json"
            flood_spec.write_text(
                json.dumps(
                    {
                        "base": base,
                        "duration_s": params.flood_duration_s,
                        "sources": [
                            loopback_address(FLOOD_NET, i) for i in range(params.flood_clients)
                        ],
                        "out": str(attempts),
                    }
                )
            )
            procs["login flood clients"] = await _load_start(
                "--flood-worker", flood_spec, env=env, log=logs / "login-flood.log"
            )
        start_wall = await _load_go(list(procs.values()), delay_s=params.start_delay_s)
        await asyncio.sleep(max(0.0, start_wall - time.time()))
        await measure(
            results=results,
            topology="one",
            phase=f"login flood: {window}",
            pids={**pids, **{label: [proc.pid] for label, proc in procs.items()}},
            seconds=params.flood_duration_s,
            names=names,
            db=db,
            workers=workers,
        )
        for proc in procs.values():
            await proc.communicate()
        rows = await asyncio.to_thread(_read_api_rows, out, window, start_wall)
        results.flood_api_rows += rows
        if window == "during":
            results.flood_attempts = await asyncio.to_thread(
                _read_flood_rows, attempts, window, start_wall
            )


async def run_async(
    params: Params,
    *,
    world: World,
    env: dict[str, str],
    logs: Path,
    results: Results,
    tree: PlatformTree,
    db: PlatformQueries,
) -> None:
    """The phases ``params.phases`` asks for, in order (see the module docstring), the
    platform being ``tree`` in ``params.topology``; children stopped on the way out."""
    first = world.light[: params.agents]
    light = [s.name for s in first]
    loaded = f"{params.agents} agents"
    workers = AgentWorkers()
    # SIGTERM cancels the run, which unwinds the stack below: every platform process,
    # worker and proxy this run started is stopped.
    loop = asyncio.get_running_loop()
    main = asyncio.current_task()
    assert main is not None
    with contextlib.suppress(ValueError, RuntimeError):  # not the main thread
        loop.add_signal_handler(signal.SIGTERM, main.cancel)
    async with contextlib.AsyncExitStack() as stack:
        stack.push_async_callback(workers.stop)
        two = params.two_processes
        shape = params.shape()
        with results.timed(f"start the platform ({params.topology}) and nginx"):
            # Process 2 of phase 4 waits, idle, until then: starting both now saves a
            # start-up.
            platform = await topology_start(
                shape, tree=tree, env=env, logs=logs, extra_single=1 if two else 0
            )
            stack.push_async_callback(platform.stop)
        base, ws_url = platform.base, platform.ws_url
        serving = {k: v for k, v in platform.roles.items() if k.startswith("platform")}
        others = {k: v for k, v in platform.roles.items() if not k.startswith("platform")}

        # --- 1. idle, then N agents ----------------------------------------------------
        with results.timed("1. idle window"):
            await asyncio.sleep(params.settle_s)
            await measure(
                results=results,
                topology="one",
                phase="0 agents",
                pids=dict(platform.roles),
                seconds=params.window_s,
                names=light,
                db=db,
                workers=workers,
            )
        cars = [s.name for s in world.cars]
        sessions: dict[bool, CarSession] = {}
        if world.cars:
            probes = await cars_start(stack, world=world, url=ws_url)
            await wait_online(names=cars, workers=workers, expect_uplinks=0, within=60, db=db)
            sessions = await car_sessions_open(
                base=base, token=world.driver_token, probes=probes, results=results
            )

        async def sessions_end() -> None:
            for session in sessions.values():
                with contextlib.suppress(ApiRefused, OSError):
                    path = f"/api/v1/sessions/{session.session_id}/end"
                    await api(base, world.driver_token, "POST", path)

        stack.push_async_callback(sessions_end)
        started = 0

        def helpers() -> dict[str, Pids]:
            return {
                **others,
                "agent workers": [c.pid for c in workers.children],
                f"this process ({len(cars)} cars, orchestration, queries)": [
                    os.getpid(),
                    db.pid,
                ],
                "postgres (all databases)": "postgres",
                "redis-server": "redis-server",
            }

        async def grow(count: int, *, key: str) -> None:
            """More agents join, in worker processes of their own, up to ``count``."""
            nonlocal started
            stage = [s.name for s in world.light[:count]]
            # agent_workers processes for the whole fleet, shared out by stage.
            share = max(1, round(params.agent_workers * (count - started) / params.light_agents))
            await workers.start(
                specs=world.light[started:count],
                world=world,
                url=ws_url,
                workers=share,
                ramp_per_s=params.ramp_per_s,
                env=env,
                logs=logs,
            )
            started = count
            wait = 30 + count / 20
            results.online_after_s[key] = await wait_online(
                names=stage + cars, workers=workers, expect_uplinks=count, within=wait, db=db
            )
            if results.online_after_s[key] is None:
                results.notes.append(
                    f"{key}: not every vehicle was online together within {wait:.0f} s of "
                    "the agents starting; the run went on (see the online counts)."
                )

        for count in params.stages():
            with results.timed(f"1. up to {count} agents connect"):
                await grow(count, key=f"one, {count} agents")
            with results.timed(f"1. {count} agents window"):
                await asyncio.sleep(params.settle_s)
                await measure(
                    results=results,
                    topology="one",
                    phase=f"{count} agents",
                    pids={**serving, **helpers()},
                    seconds=params.window_s,
                    names=[s.name for s in world.light[:count]],
                    db=db,
                    workers=workers,
                )
        if params.phases != "heartbeats":
            # --- 2 and 3 on the topology ---------------------------------------------
            pids = {**serving, **helpers()}
            with results.timed("2. API load"):
                await load_phase(
                    topology="one",
                    results=results,
                    params=params,
                    world=world,
                    base=base,
                    env=env,
                    logs=logs,
                    workers=workers,
                    pids=pids,
                    names=light,
                    sessions=sessions,
                    db=db,
                )
            with results.timed("3. link-loss trials"):
                results.trials += await reaction_trials(
                    topology="one",
                    modes=MODES,
                    n=params.trials,
                    base=base,
                    token=world.driver_token,
                    sessions=sessions,
                    results=results,
                    budget_s=params.trial_budget_s,
                    db=db,
                )
            if params.flood_clients:
                with results.timed("5. login flood (API alone, then with the flood)"):
                    await flood_phase(
                        results=results,
                        params=params,
                        world=world,
                        base=base,
                        env=env,
                        logs=logs,
                        workers=workers,
                        pids=pids,
                        names=light,
                        db=db,
                    )
        if params.fleet_agents > params.agents:
            # --- 6. the fleet grown, heartbeats only -----------------------------------
            count = params.fleet_agents
            with results.timed(f"6. up to {count} agents connect"):
                await grow(count, key=f"one, {count} agents (fleet phase)")
            with results.timed(f"6. {count} agents window"):
                await asyncio.sleep(params.settle_s)
                await measure(
                    results=results,
                    topology="one",
                    phase=f"{count} agents",
                    pids={**serving, **helpers()},
                    seconds=params.window_s,
                    names=[s.name for s in world.light[:count]],
                    db=db,
                    workers=workers,
                )
        if not two or params.phases == "heartbeats":
            return

        # --- 4. two processes behind nginx ----------------------------------------------
        p1, p2 = platform.children[0], platform.children[1]
        with results.timed("4. nginx restarted, agents reconnect"):
            registered = workers.registrations
            # WebSockets (the agents' uplinks, the relay) to process 1, HTTP to process 2.
            await proxy_reroute(platform, web=[p2.port], ws=[p1.port], logs=logs)
            key = "two, all reconnect"
            results.online_after_s[key] = await wait_online(
                names=[s.name for s in world.light[:started]] + cars,
                workers=workers,
                expect_uplinks=started,
                within=30 + started / 20,
                db=db,
                registrations_at_least=registered + started,
            )
        if results.online_after_s[key] is None:
            results.notes.append(
                "two processes: not every vehicle was online together within "
                f"{30 + started / 20:.0f} s of nginx's restart; the run went on (see the "
                "online counts)."
            )
        pids = {"platform-1 (agents)": [p1.pid], "platform-2 (users)": [p2.pid], **helpers()}
        pids.update({k: v for k, v in platform.roles.items() if not k.startswith("platform")})
        with results.timed("4. agents window, two processes"):
            await asyncio.sleep(params.settle_s)
            await measure(
                results=results,
                topology="two",
                phase=loaded,
                pids=pids,
                seconds=params.window_s,
                names=light,
                db=db,
                workers=workers,
            )
        with results.timed("4. API load, two processes"):
            await load_phase(
                topology="two",
                results=results,
                params=params,
                world=world,
                base=base,
                env=env,
                logs=logs,
                workers=workers,
                pids=pids,
                names=light,
                sessions=sessions,
                db=db,
            )
        with results.timed("4. relayed link-loss trials, two processes"):
            results.trials += await reaction_trials(
                topology="two",
                modes=[m for m in MODES if m.startswith("relay")],
                n=params.trials,
                base=base,
                token=world.driver_token,
                sessions=sessions,
                results=results,
                budget_s=params.trial_budget_s,
                db=db,
            )


#: What to count in the platform processes' output (the server's access or error log
#: and Django's log): label -> a pattern matching daphne's line or uvicorn's.
LOG_PATTERNS = {
    label: re.compile(pattern)
    for label, pattern in {
        "uplinks accepted": r'"WSCONNECT /ws/agent/"|"WebSocket /ws/agent/" \[accepted\]',
        "WebSocket handshakes rejected": r'"WSREJECT |"WebSocket [^"]*" 403',
        "Redis pool exhausted (MaxConnectionsError)": r"redis\.exceptions\.MaxConnectionsError",
        "errors logged (ERROR)": r" ERROR |^ERROR:",
        "tracebacks": r"Traceback \(most recent call last\)",
        "consumers slow to shut down": r"took too long to shut down",
    }.items()
}


#: The platform's processes' logs (``<name>.log`` in the run's folder), by name.
PLATFORM_LOGS = ("platform-", "gunicorn-", "uvicorn-", "iouv-worker", "iouv-beat")


def log_counts(path: Path) -> dict[str, int]:
    """How many lines of a platform process's output match each of LOG_PATTERNS."""
    counts = dict.fromkeys(LOG_PATTERNS, 0)
    with open(path, errors="replace") as f:
        for line in f:
            for label, pattern in LOG_PATTERNS.items():
                if pattern.search(line):
                    counts[label] += 1
    return counts


def _code_label(tree: PlatformTree) -> str:
    """The platform's code as the report names it."""
    if tree.commit:
        return f"{tree.label} ({tree.commit[:10]}, a git worktree)"
    done = subprocess.run(
        ["git", "describe", "--always", "--dirty"], cwd=ROOT, capture_output=True, text=True
    )
    return f"the checkout ({done.stdout.strip() or 'not a git checkout'})"


def run(
    params: Params,
    *,
    out: Path,
    command: str,
    database_url: str,
    tree: PlatformTree | None = None,
    prepare: bool = False,
) -> Results:
    """Run the phases ``params`` asks for against ``tree``'s platform (default: this
    checkout) and write the outputs to ``out``; returns the results.

    The database ``database_url`` names must exist; with ``prepare`` the tree migrates
    and empties it first, else it must be migrated and empty already. REDIS_URL,
    CHANNELS_PREFIX and IOUV_VAR_DIR are taken from the environment, which the children
    inherit. Raises :class:`benchmarks.scale_platform.PlatformQueryError` when the
    tree's code cannot set the run up.
    """
    raise_open_files_limit()
    tree = tree or PlatformTree()
    env = {
        **os.environ,
        "DATABASE_URL": database_url,
        "PYTHONUNBUFFERED": "1",
        # Per-connection INFO lines would put a thousand log writes in the measurement.
        "LOG_LEVEL": os.environ.get("BENCH_LOG_LEVEL", "WARNING"),
        # A few API clients request sessions and grants far faster than any user may
        # (services.web.throttle): the benchmark measures the platform, not its limits.
        "IOUV_RATE_LIMITS": "0",
        # The two car sessions are opened once and driven phase after phase, with nobody
        # connected in between (the agents' reconnection, a measurement window): on a
        # busy machine that outlasts the 30 s a driver has to come back, and the 120 s
        # to connect at all, and supervision ended them before the second topology used
        # them (409 on their grant). The benchmark keeps them for the whole run.
        "IOUV_RECONNECT_GRACE_S": "3600",
        "IOUV_CONNECT_TIMEOUT_S": "3600",
        # The settings' default is inside the tree: every tree must share the signing
        # key and the logs.
        "IOUV_VAR_DIR": os.environ.get("IOUV_VAR_DIR", str(ROOT / "var")),
    }
    logs = (
        Path(env["IOUV_VAR_DIR"])
        / "bench-scale"
        / f"{tree.label}-{params.server}-{params.topology}".replace("/", "_")
    )
    logs.mkdir(parents=True, exist_ok=True)
    for old in logs.glob("*.log"):
        old.unlink()  # an earlier run's: its processes' logs would be counted
    # nginx speaks TLS with the run's own CA (made when it first starts): every client,
    # in this process (for the run only) and its children, trusts it.
    env["SSL_CERT_FILE"] = str(ca_file(logs))
    trusted = os.environ.get("SSL_CERT_FILE")
    results = Results(
        params=params,
        machine=machine_info(),
        command=command,
        database=database_url.rsplit("@", 1)[-1],
    )
    results.machine["server"] = params.server
    results.machine["topology"] = params.shape().describe()
    results.machine["platform_code"] = _code_label(tree)
    os.environ["SSL_CERT_FILE"] = env["SSL_CERT_FILE"]
    try:
        asyncio.run(
            _run_with_queries(
                params, tree=tree, env=env, logs=logs, results=results, prepare=prepare
            )
        )
    finally:
        if trusted is None:
            os.environ.pop("SSL_CERT_FILE", None)
        else:
            os.environ["SSL_CERT_FILE"] = trusted
        for path in sorted(logs.glob("*.log")):
            if path.stem.startswith(PLATFORM_LOGS):
                results.log_counts[path.stem] = log_counts(path)
    write_outputs(results, out)
    return results


async def _run_with_queries(
    params: Params,
    *,
    tree: PlatformTree,
    env: dict[str, str],
    logs: Path,
    results: Results,
    prepare: bool,
) -> None:
    """Set the world up with the tree's own code, then run the phases."""
    async with PlatformQueries(tree, env=env, log=logs / "queries.log") as db:
        if prepare:
            with results.timed("migrate and empty the database"):
                await db.call("prepare")
        with results.timed("register vehicles, users and tokens"):
            world = World.from_json(
                await db.call(
                    "world_build",
                    light=params.light_agents,
                    cars=params.cars_needed,
                    clients=params.api_clients,
                    link_loss_timeout_ms=params.link_loss_timeout_ms,
                )
            )
        platform_settings = await db.call("settings")
        results.machine["db_conn_max_age"] = env.get("DB_CONN_MAX_AGE", "60 (default)")
        results.machine["db_pool_size"] = env.get("DB_POOL_SIZE", "16 (default)")
        for key in ("http_concurrency", "heartbeat_s", "offline_after_s"):
            results.machine[key] = platform_settings[key]
        await run_async(params, world=world, env=env, logs=logs, results=results, tree=tree, db=db)


# ======================================================================================
# Outputs
# ======================================================================================


def _write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for row in rows:
            writer.writerow([f"{v:.3f}" if isinstance(v, float) else v for v in row])


def _per_heartbeat_ms(cpu_pct: float, heartbeats_per_s: float) -> float | None:
    """Milliseconds of CPU per heartbeat: CPU (percent of one core) over heartbeats per
    second; None without heartbeats."""
    return cpu_pct * 10 / heartbeats_per_s if heartbeats_per_s else None


def topologies(params: Params) -> list[str]:
    """The topologies the API phases ran in."""
    if params.phases == "heartbeats":
        return []
    return ["one", "two"] if params.two_processes else ["one"]


def platform_usage(results: Results, topology: str, phase: str) -> Usage:
    """The processes serving requests (labels starting with ``platform``: the single
    process, or gunicorn's and uvicorn's) over one window, summed; their threads are
    shown when there is one process."""
    rows = [
        u
        for u in results.usage
        if (u.topology, u.phase) == (topology, phase) and u.process.startswith("platform")
    ]
    if not rows:
        raise KeyError(f"no platform usage for {topology}/{phase}")
    return Usage(
        phase,
        topology,
        " + ".join(u.process for u in rows),
        rows[0].window_s,
        sum(u.cpu_pct for u in rows),
        sum(u.rss_mb for u in rows),
        rows[0].threads if len(rows) == 1 else "",
    )


def roles_cpu(results: Results) -> dict[str, dict[str, float]]:
    """CPU (% of one core) per process role and window of the topology under test:
    ``"<phase>" -> {role: cpu}``, the roles being the platform's processes (gunicorn,
    uvicorn, or the single one), nginx, Celery, and the whole machine."""
    out: dict[str, dict[str, float]] = {}
    for u in results.usage:
        if u.topology != "one":
            continue
        if u.process.startswith(("platform", "nginx", "celery", "whole machine")):
            out.setdefault(u.phase, {})[u.process] = u.cpu_pct
    return out


def flood_figures(results: Results) -> dict[str, Any]:
    """The login flood's figures: the API's latency per endpoint without and during
    the flood, and what the flood's attempts were answered."""
    p = results.params
    api_: dict[str, Any] = {}
    for window in FLOOD_WINDOWS:
        rows = [r for r in results.flood_api_rows if r["topology"] == window]
        ok = [r for r in rows if 200 <= r["status"] < 300]
        statuses: dict[str, int] = {}
        for r in rows:
            key = f"{r['endpoint']} {r['status']}"
            statuses[key] = statuses.get(key, 0) + 1
        api_[window] = {
            "services_ms": summary(r["latency_ms"] for r in ok if r["endpoint"] == "services"),
            "request_ms": summary(r["latency_ms"] for r in ok if r["endpoint"] == "request"),
            "end_ms": summary(r["latency_ms"] for r in ok if r["endpoint"] == "end"),
            "all_ms": summary(r["latency_ms"] for r in ok),
            "sessions_per_s": sum(r["endpoint"] == "request" for r in ok) / p.flood_duration_s,
            "statuses": statuses,
        }
    answers: dict[str, int] = {}
    for a in results.flood_attempts:
        key = str(a["status"]) + (f" ({a['answered_by']})" if a["answered_by"] else "")
        answers[key] = answers.get(key, 0) + 1
    return {
        "clients": p.flood_clients,
        "duration_s": p.flood_duration_s,
        "attempts": len(results.flood_attempts),
        "attempts_per_s": len(results.flood_attempts) / p.flood_duration_s,
        "attempt_ms": summary(a["latency_ms"] for a in results.flood_attempts),
        "answers": answers,
        "api": api_,
    }


def figures(results: Results) -> dict[str, Any]:
    """The aggregate figures the report shows (also written to summary.json).

    ``cpu_ms_per_heartbeat``: all the platform process's CPU over the window divided by
    the heartbeats the light agents sent in it (an upper bound: the process does nothing
    else then but its idle work and the agents' keepalive pings);
    ``cpu_ms_per_heartbeat_over_idle`` subtracts the idle process's CPU first.
    """
    p = results.params
    loaded_phase = f"{p.agents} agents"
    idle = platform_usage(results, "one", "0 agents")
    loaded = platform_usage(results, "one", loaded_phase)
    fleet = results.fleet[f"one/{loaded_phase}"]
    updates = fleet["vehicle_updates_per_s"]
    heartbeats = fleet["heartbeats_per_s"]
    out: dict[str, Any] = {
        "server": p.server,
        "code": results.machine.get("platform_code", ""),
        "agents": {
            "n": p.agents,
            "idle_cpu_pct": idle.cpu_pct,
            "idle_rss_mb": idle.rss_mb,
            "cpu_pct": loaded.cpu_pct,
            "rss_mb": loaded.rss_mb,
            "threads": loaded.threads,
            "cpu_pct_per_agent": (loaded.cpu_pct - idle.cpu_pct) / p.agents,
            "rss_kb_per_agent": (loaded.rss_mb - idle.rss_mb) * 1024 / p.agents,
            "heartbeats_per_s": heartbeats,
            "cpu_ms_per_heartbeat": _per_heartbeat_ms(loaded.cpu_pct, heartbeats),
            "cpu_ms_per_heartbeat_over_idle": _per_heartbeat_ms(
                loaded.cpu_pct - idle.cpu_pct, heartbeats
            ),
            "online_min": fleet["online_min"],
            "vehicle_updates_per_s": updates,
            # All of the process's CPU over what it stored: an upper bound per update.
            "cpu_ms_per_update": loaded.cpu_pct * 10 / updates if updates else None,
            "online_after_s": results.online_after_s,
        },
        "stages": [],
        "roles": roles_cpu(results),
        "fleet": results.fleet,
        "api": {},
        "relay": {},
        "reaction": {},
    }
    counts = p.stages() + ([p.fleet_agents] if p.fleet_agents > p.agents else [])
    for count in counts:
        u = platform_usage(results, "one", f"{count} agents")
        f = results.fleet[f"one/{count} agents"]
        out["stages"].append(
            {
                "agents": count,
                "cpu_pct": u.cpu_pct,
                "rss_mb": u.rss_mb,
                "threads": u.threads,
                "cpu_pct_per_agent": (u.cpu_pct - idle.cpu_pct) / count,
                "rss_kb_per_agent": (u.rss_mb - idle.rss_mb) * 1024 / count,
                "online_min": f["online_min"],
                "online_mean": f["online_mean"],
                "heartbeat_age_s": f["heartbeat_age_s"],
                "heartbeats_per_s": f["heartbeats_per_s"],
                "cpu_ms_per_heartbeat": _per_heartbeat_ms(u.cpu_pct, f["heartbeats_per_s"]),
                "vehicle_updates_per_s": f["vehicle_updates_per_s"],
            }
        )
    if p.fleet_agents > p.agents:
        out["fleet_phase"] = out["stages"][-1]
    if results.flood_api_rows or results.flood_attempts:
        out["flood"] = flood_figures(results)
    for topology in topologies(p):
        rows = [r for r in results.api_rows if r["topology"] == topology]
        ok = [r for r in rows if 200 <= r["status"] < 300]
        duration = p.api_duration_s
        done = [r for r in ok if r["start_s"] + r["latency_ms"] / 1000 <= duration]
        delivered = [
            d["delivery_ms"]
            for d in results.deliveries
            if d["topology"] == topology and d["delivery_ms"] is not None
        ]
        statuses: dict[str, int] = {}
        for r in rows:
            key = f"{r['endpoint']} {r['status']}"
            statuses[key] = statuses.get(key, 0) + 1
        out["api"][topology] = {
            "clients": p.api_clients,
            "rate": p.api_rate,
            "duration_s": duration,
            "requests_per_s": len(done) / duration,
            "sessions_per_s": sum(r["endpoint"] == "request" for r in done) / duration,
            "request_ms": summary(r["latency_ms"] for r in ok if r["endpoint"] == "request"),
            "end_ms": summary(r["latency_ms"] for r in ok if r["endpoint"] == "end"),
            "statuses": statuses,
            "task_delivery_ms": summary(delivered),
            "sessions": results.sessions.get(topology, {}),
        }
        rtts, lost = results.relay.get(topology, ([], 0))
        out["relay"][topology] = {**summary(rtts), "lost": lost}
        for mode in MODES:
            trials = [t for t in results.trials if t.topology == topology and t.mode == mode]
            if trials:
                out["reaction"][f"{topology}/{mode}"] = {
                    "reaction_ms": summary(t.reaction_ms for t in trials),
                    "agent_ms": summary(t.agent_ms for t in trials),
                    "platform_logged": sum(t.platform_logged for t in trials),
                }
    return out


def write_outputs(results: Results, out: Path) -> None:
    """The CSVs, summary.json and report.md."""
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(
        out / "resources.csv",
        ["topology", "phase", "process", "window_s", "cpu_pct_of_one_core", "rss_mb", "threads"],
        (
            (u.topology, u.phase, u.process, u.window_s, u.cpu_pct, u.rss_mb, u.threads)
            for u in results.usage
        ),
    )
    _write_csv(
        out / "api_requests.csv",
        ["topology", "client", "endpoint", "start_s", "latency_ms", "status", "session_id"],
        (
            [r[k] for k in ("topology", "client", "endpoint", "start_s", "latency_ms", "status")]
            + [r["session_id"]]
            for r in results.api_rows
        ),
    )
    _write_csv(
        out / "task_delivery.csv",
        ["topology", "session_id", "request_to_agent_ms"],
        (
            (d["topology"], d["session_id"], "" if d["delivery_ms"] is None else d["delivery_ms"])
            for d in results.deliveries
        ),
    )
    _write_csv(
        out / "relay_rtt.csv",
        ["topology", "n", "rtt_ms"],
        (
            (topology, i, rtt)
            for topology, (rtts, _) in results.relay.items()
            for i, rtt in enumerate(rtts)
        ),
    )
    _write_csv(
        out / "reaction_trials.csv",
        ["topology", "mode", "trial", "reaction_ms", "agent_side_ms", "platform_logged"],
        (
            (t.topology, t.mode, t.trial, t.reaction_ms, t.agent_ms, int(t.platform_logged))
            for t in results.trials
        ),
    )
    _write_csv(
        out / "login_flood.csv",
        ["window", "client", "start_s", "latency_ms", "status", "answered_by"],
        (
            [a[k] for k in ("window", "client", "start_s", "latency_ms", "status", "answered_by")]
            for a in results.flood_attempts
        ),
    )
    _write_csv(
        out / "flood_api_requests.csv",
        ["window", "client", "endpoint", "start_s", "latency_ms", "status", "session_id"],
        (
            [r[k] for k in ("topology", "client", "endpoint", "start_s", "latency_ms", "status")]
            + [r["session_id"]]
            for r in results.flood_api_rows
        ),
    )
    data = figures(results)
    document = {
        "command": results.command,
        "machine": results.machine,
        "params": asdict(results.params),
        "figures": data,
        "platform_logs": results.log_counts,
        "notes": results.notes,
    }
    (out / "summary.json").write_text(json.dumps(document, indent=2) + "\n")
    (out / "report.md").write_text(report_md(results, data))


def _q(s: dict[str, float], *keys: str, sep: str = " / ") -> str:
    """Figures of a summary for a table cell ("n/a" for an empty one)."""
    if not s.get("n", 1):
        return sep.join("n/a" for _ in keys)
    return sep.join(f"{s[k]:.0f}" if s[k] >= 10 else f"{s[k]:.1f}" for k in keys)


def _ms(value: float | None) -> str:
    """A per-heartbeat figure in ms for the report ("n/a" without heartbeats)."""
    return "n/a" if value is None else f"{value:.3f}"


def _change(before: float, after: float) -> str:
    if not before or math.isnan(before) or math.isnan(after):
        return "n/a"
    return f"{before:.1f} → {after:.1f} ({100 * (after - before) / before:+.0f} %)"


def report_md(results: Results, data: dict[str, Any]) -> str:
    """The human report: summary first, then each phase's tables and the notes."""
    p, m = results.params, results.machine
    agents, api_, relay, reaction = data["agents"], data["api"], data["relay"], data["reaction"]
    loaded = f"{p.agents} agents"
    fleet_one = results.fleet[f"one/{loaded}"]
    hb = float(m["heartbeat_s"])
    server = p.server
    serving = (
        f"one {server} process"
        if p.topology == "single"
        else "the production shape's processes (gunicorn, uvicorn)"
    )

    def cpu(topology: str, phase: str, process: str) -> float:
        for u in results.usage:
            if (u.topology, u.phase, u.process) == (topology, phase, process):
                return u.cpu_pct
        return float("nan")

    lines: list[str] = []
    add = lines.append
    add("# Scale benchmark: agents, assignment and deployment, link loss, two processes")
    add("")
    add(f"Generated by `{results.command}` (`benchmarks/scale.py`) on {m['date_utc']}; raw data")
    add("in the CSV files beside this report, every figure in `summary.json`.")
    add("")
    add(
        f"**Every platform figure below was served by {m.get('topology', server)}** "
        f"(`iouv.asgi`/`iouv.wsgi`, {m.get('platform_code', 'this checkout')}): nginx with "
        "the shipped site (`deploy/nginx/iouv.conf`: TLS, routing by path, per-address "
        "limits) in front. Where a figure says *process*, read the topology's platform "
        "processes together (gunicorn's and uvicorn's in production)."
    )
    if p.quick:
        add("")
        add("**Quick mode: a smoke test of the benchmark, not a measurement.**")
    add("")
    add("## Summary")
    add("")
    all_online = fleet_one["online_min"] == p.agents
    held = (
        f"all {p.agents} were online throughout the window"
        if all_online
        else f"only {fleet_one['online_min']} to {fleet_one['online']} of {p.agents} counted as "
        f"online at once (mean {fleet_one['online_mean']:.0f}): of the "
        f"{agents['heartbeats_per_s']:.0f} heartbeats/s sent, the platform recorded the last "
        f"{fleet_one['heartbeat_age_s']['p50']:.1f} s ago (p50) against an offline threshold "
        f"of {m['offline_after_s']:g} s"
    )
    add(
        f"* **{p.agents} agents** on uplinks to {serving}, heartbeating every "
        f"{hb:g} s: the process used **{agents['cpu_pct']:.0f} % of one core and "
        f"{agents['rss_mb']:.0f} MB** resident (idle: {agents['idle_cpu_pct']:.1f} %, "
        f"{agents['idle_rss_mb']:.0f} MB), that is **{agents['cpu_pct_per_agent']:.3f} % of a "
        f"core and {agents['rss_kb_per_agent']:.0f} KiB per agent** and "
        f"**{_ms(agents['cpu_ms_per_heartbeat'])} ms of its CPU per heartbeat** "
        f"({agents['heartbeats_per_s']:.0f} heartbeats/s sent); {held}."
    )
    kept = [st for st in data["stages"] if st["online_min"] == st["agents"]]
    if len(data["stages"]) > 1:
        first = data["stages"][0]
        add(
            "  On the way up: "
            + (
                f"up to {kept[-1]['agents']} agents all stayed online "
                f"({kept[-1]['cpu_pct']:.0f} % of a core, {kept[-1]['cpu_pct_per_agent']:.3f} % "
                f"and {kept[-1]['rss_kb_per_agent']:.0f} KiB per agent)"
                if kept
                else f"already at {first['agents']} agents not all stayed online "
                f"(min {first['online_min']}, {first['cpu_pct']:.0f} % of a core, "
                f"{first['cpu_pct_per_agent']:.3f} % and {first['rss_kb_per_agent']:.0f} KiB "
                "per agent)"
            )
            + "; see section 1."
        )
    silent = reaction.get("one/direct_silent")
    if silent:
        parts = []
        for key, v in reaction.items():
            if key.startswith("one/"):
                r = v["reaction_ms"]
                parts.append(
                    f"{key.split('/')[1].replace('_', ' ')}: {_q(r, 'min', 'p50', 'p95', 'max')} ms"
                )
        add(
            "* **Link loss to safe action** (last input, or the socket's death, to the car's "
            f"stop; min / p50 / p95 / max over {p.trials} trials each; link-loss timeout "
            f"{p.link_loss_timeout_ms} ms; {p.agents} agents connected): " + "; ".join(parts) + "."
        )
    one = api_.get("one")
    two = api_.get("two")
    if one:
        both = (
            f"; two processes, agents on one and users on the other, "
            f"**{two['sessions_per_s']:.1f} sessions/s** ({two['requests_per_s']:.1f} "
            f"requests/s; {_q(two['request_ms'], 'p50', 'p95')} ms)"
            if two
            else ""
        )
        add(
            f"* **Assignment + deployment** ({_api_load(p)}, each "
            f"session requested, deployed to a live agent and ended): {serving} sustained "
            f"**{one['sessions_per_s']:.1f} sessions/s** ({one['requests_per_s']:.1f} "
            f"requests/s; request p50 / p95 {_q(one['request_ms'], 'p50', 'p95')} ms){both}. "
            "Relayed command round trip p50 / p95 under that load: "
            + "; ".join(
                f"{_q(relay[t], 'p50', 'p95')} ms "
                + ("with two processes" if t == "two" else f"on {serving}")
                for t in relay
            )
            + "."
        )
    add("")
    add("## Machine and run")
    add("")
    add("| | |")
    add("|---|---|")
    for key, label in (
        ("topology", "platform topology (benchmarks.scale_topology)"),
        ("server", "ASGI server of the platform processes"),
        ("platform_code", "platform code"),
        ("cpu_model", "CPU"),
        ("cores", "cores"),
        ("ram_gb", "RAM (GB)"),
        ("os", "OS"),
        ("python", "Python"),
        ("date_utc", "date"),
        ("load_average_at_start", "load average at start (1, 5, 15 min)"),
        ("open_files_limit", "open files limit"),
        ("db_conn_max_age", "DB_CONN_MAX_AGE of the platform (without a pool)"),
        ("db_pool_size", "DB_POOL_SIZE of the platform (a tree older than the pool has none)"),
        (
            "http_concurrency",
            "IOUV_HTTP_CONCURRENCY (HTTP requests at once per process; None: no such limit)",
        ),
        ("heartbeat_s", "IOUV_HEARTBEAT_INTERVAL_S"),
        ("offline_after_s", "IOUV_OFFLINE_AFTER_S"),
    ):
        add(f"| {label} | {m.get(key)} |")
    add(f"| command | `{results.command}` |")
    add(
        "| run time | "
        + ", ".join(f"{name} {seconds:.0f} s" for name, seconds in results.timings.items())
        + " |"
    )
    add(f"| database | `{results.database}` (created, migrated and emptied by the run) |")
    add("")
    add("The machine is shared: everything below (platform, PostgreSQL, Redis, proxy, agents,")
    add("API clients) ran on it at once, and so may other people's work. The load generators'")
    add("own CPU is listed beside the platform's, and so is the whole machine's.")
    add("")
    add("| parameter | value |")
    add("|---|---|")
    for key, value in asdict(p).items():
        add(f"| `{key}` | {value} |")
    add("")
    add(f"**Real**: {m.get('topology', server)}, PostgreSQL, the Redis")
    add("channel layer, the platform's signing key, vehicles and API tokens in the database,")
    add("assignment, signed task deployment, supervision, the relay; every agent runs the real")
    add("`agents.uplink.Uplink` client; the two cars are full agents (`agents.runtime.Agent`,")
    add("car adapter on gpiozero mock pins with its simulated world). **Light**: the light")
    add("agents have no adapter and no video; they verify and accept tasks, and heartbeat.")
    add("The Celery worker and beat run as `deploy/systemd`'s units start them (periodic")
    add("sweeps and supervision timers). All traffic went through nginx (Debian's package in")
    add("one process) with the shipped site, over TLS, every light agent, API client and")
    add("flood client from an address of its own in 127.0.0.0/8, as nginx's per-address")
    add("limits would see a fleet and its users (`benchmarks.scale_topology`).")
    add("")

    add(f"## 1. {p.agents} agents on uplinks")
    add("")
    after = ", ".join(
        f"{k}: {f'{v:.1f} s' if v is not None else 'not within the time limit'}"
        for k, v in agents["online_after_s"].items()
    )
    add(
        f"The uplinks opened at about {p.ramp_per_s:g} per second. Time until every vehicle was "
        f"online at once (as the platform counts them): {after}. CPU is the share of one core over "
        f"{p.window_s:g} s from `/proc/<pid>/stat` (user + system, all threads), memory is "
        "VmRSS; *threads* are the platform process's busiest threads (and how many it has)."
    )
    add("")
    add("On the way up (one process; CPU of one core, per agent over the idle process):")
    add("")
    add(
        "| agents | CPU % | RSS MB | per agent: CPU % / KiB | heartbeats sent per s | CPU ms "
        "per heartbeat | online min / mean | heartbeat age p50 / p95 (s) | vehicle rows "
        "updated per s |"
    )
    add("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for st in data["stages"]:
        age = st["heartbeat_age_s"]
        add(
            f"| {st['agents']} | {st['cpu_pct']:.0f} | {st['rss_mb']:.0f} | "
            f"{st['cpu_pct_per_agent']:.3f} / {st['rss_kb_per_agent']:.0f} | "
            f"{st['heartbeats_per_s']:.0f} | {_ms(st['cpu_ms_per_heartbeat'])} | "
            f"{st['online_min']} / {st['online_mean']:.0f} | {age['p50']:.1f} / {age['p95']:.1f} | "
            f"{st['vehicle_updates_per_s']:.0f} |"
        )
    add("")
    add(
        "*CPU ms per heartbeat*: the platform process's CPU seconds over the window divided "
        "by the heartbeats the light agents sent in it (each agent counts its own; the "
        "rate is taken between the workers' once-a-second reports). It is all of the "
        "process's CPU, idle work and the agents' keepalive pings included: an upper bound."
    )
    add("")
    add("Every process, idle and with all the agents:")
    add("")
    add("| topology | phase | process | CPU % of one core | RSS MB | threads |")
    add("|---|---|---|---:|---:|---|")
    for u in results.usage:
        if u.phase in ("0 agents", loaded):
            rss = f"{u.rss_mb:.0f}" if u.rss_mb else ""
            add(
                f"| {u.topology} | {u.phase} | {u.process} | {u.cpu_pct:.1f} | {rss} | "
                f"{u.threads} |"
            )
    add("")
    add("The fleet as the platform saw it (light agents only):")
    add("")
    add(
        "| topology / phase | online at end | online min / mean | heartbeat age p50 / p95 / max "
        "(s) | vehicle updates/s | DB connections (this DB / server) |"
    )
    add("|---|---:|---:|---:|---:|---:|")
    for key, f in results.fleet.items():
        age = f["heartbeat_age_s"]
        add(
            f"| {key} | {f['online']} of {f['of']} | {f['online_min']} / {f['online_mean']:.0f} | "
            f"{age['p50']:.1f} / {age['p95']:.1f} / {age['max']:.1f} | "
            f"{f['vehicle_updates_per_s']:.0f} | {f['db_conns']} / {f['db_conns_all']} |"
        )
    add("")
    add(
        f"Per agent (one process, {p.agents} agents minus idle): "
        f"**{agents['cpu_pct_per_agent']:.3f} % of a core** and "
        f"**{agents['rss_kb_per_agent']:.0f} KiB**. The agents sent "
        f"{agents['heartbeats_per_s']:.0f} heartbeats/s: "
        f"**{_ms(agents['cpu_ms_per_heartbeat'])} ms of the process's CPU per heartbeat** "
        f"({_ms(agents['cpu_ms_per_heartbeat_over_idle'])} ms over the idle process). "
        f"PostgreSQL's counter shows {agents['vehicle_updates_per_s']:.0f} vehicle-row "
        "updates/s (heartbeats the platform writes to the vehicle's row, profiles, status "
        "changes)."
    )
    add("")
    if not one:
        return _report_end(results, data, lines)

    add("## 2. Assignment and task deployment")
    add("")
    add(
        f"{_api_load(p)}, each client its own user with a bearer token, "
        f"for {p.api_duration_s:g} s: `POST /api/v1/sessions` (assignment among the online idle "
        "drones, nearest to a random target within 1 km; a signed task deployed to the chosen "
        "light agent over its uplink; the user task returned), then `POST .../end`. Meanwhile "
        f"a relayed control session sent commands at {p.relay_hz:g} Hz through the platform to "
        "a car, each waiting for its ack. *Delivery*: from the request's start to the task's "
        "arrival at the agent (wall clocks of one machine)."
    )
    add("")
    tops = [t for t in ("one", "two") if t in api_]
    heads = {"one": "one process", "two": "two processes"}
    add("| | " + " | ".join(heads[t] for t in tops) + " |")
    add("|---|" + "---:|" * len(tops))

    def table_row(label: str, cell: Any) -> None:
        add(f"| {label} | " + " | ".join(str(cell(t)) for t in tops) + " |")

    table_row("sessions per s", lambda t: f"{api_[t]['sessions_per_s']:.1f}")
    table_row("API requests per s", lambda t: f"{api_[t]['requests_per_s']:.1f}")
    for label, key in (
        ("request", "request_ms"),
        ("end", "end_ms"),
        ("task delivery", "task_delivery_ms"),
    ):
        table_row(
            f"{label} p50 / p95 / max (ms)", lambda t, k=key: _q(api_[t][k], "p50", "p95", "max")
        )
    table_row(
        "relayed round trip p50 / p95 / max (ms)", lambda t: _q(relay[t], "p50", "p95", "max")
    )
    table_row(f"relayed commands without ack in {LOST_AFTER_S:g} s", lambda t: relay[t]["lost"])
    table_row(
        "answers (endpoint status: count)",
        lambda t: ", ".join(f"{k}: {v}" for k, v in sorted(api_[t]["statuses"].items())),
    )

    def log_line(t: str) -> str:
        s = api_[t]["sessions"]
        if not s:
            return ""
        return f"{s['task_deployed']} / {s['task_accepted']} / {s['final']} of {s['sessions']}"

    table_row("sessions: task deployed / accepted by the agent / over (session logs)", log_line)
    add("")
    add("CPU during the load (% of one core):")
    add("")
    add("| topology | process | CPU % | RSS MB | threads |")
    add("|---|---|---:|---:|---|")
    for u in results.usage:
        if u.phase == "API load":
            rss = f"{u.rss_mb:.0f}" if u.rss_mb else ""
            add(f"| {u.topology} | {u.process} | {u.cpu_pct:.1f} | {rss} | {u.threads} |")
    add("")

    add("## 3. Link loss to safe action")
    add("")
    add(
        f"A car serving a session (link-loss timeout {p.link_loss_timeout_ms} ms, fail-safe "
        f"`stop`), {p.trials} trials per case, with the light agents connected (the cars' "
        "sessions, one reached directly and one through the relay, were opened before the "
        "fleet connected; each trial takes a fresh grant from the API). The controller "
        "drives (`forward`, then a keepalive every 50 ms), then either goes **silent** (nothing "
        "more is sent: a pulled cable or a frozen tab; the agent's watchdog fires) or its "
        "socket is **closed** abruptly (aborted: no WebSocket close handshake, what a crashed "
        "tab or browser leaves). *Reaction*: from the controller's last frame (or the close) "
        "to the adapter being told to stop, on one monotonic clock. "
        "*Agent side*: from the last frame the agent received (or the moment it saw the link "
        "close) to the stop. *Logged*: fail-safes that reached the session log as "
        "`unintentional_end`."
    )
    add("")
    add("| topology | case | n | min | p50 | p95 | max | agent side p50 / p95 | logged |")
    add("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for key, v in reaction.items():
        topology, mode = key.split("/")
        r, a = v["reaction_ms"], v["agent_ms"]
        add(
            f"| {topology} | {mode.replace('_', ' ')} | {r['n']} | "
            f"{_q(r, 'min', 'p50', 'p95', 'max', sep=' | ')} | {_q(a, 'p50', 'p95')} | "
            f"{v['platform_logged']}/{r['n']} |"
        )
    add("")
    add(
        "(ms.) A silent link cannot be told from a slow one before the timeout; the watchdog "
        f"looks every {min(50, p.link_loss_timeout_ms / 5):g} ms, hence up to that much on top. "
        "A closed direct socket is seen by the agent at once; a closed relayed socket is seen by "
        "the platform process holding it, which tells the agent through the channel layer and "
        "the agent's uplink (`relay_close`)."
    )
    add("")

    if not two:
        return _report_end(results, data, lines)
    add("## 4. One platform process against two")
    add("")
    add(
        f"Two {server} processes behind nginx (`benchmarks.nginx_proxy`) on one address, sharing "
        "PostgreSQL and Redis: `/ws/agent/` to process 1, everything else (API, relay) to "
        "process 2. The agents reconnected through the restarted proxy by themselves (backoff "
        "with jitter). Assignment on process 2, deployment to agents held by process 1, the "
        "relay across both and supervision all worked (tables above; "
        "`tests/integration/test_scale_out.py` checks it too)."
    )
    add("")
    load = "API load"
    rows = [
        ("sessions per s", f"{one['sessions_per_s']:.1f}", f"{two['sessions_per_s']:.1f}"),
        (
            "request p50 / p95 (ms)",
            _q(one["request_ms"], "p50", "p95"),
            _q(two["request_ms"], "p50", "p95"),
        ),
        (
            "task delivery p50 / p95 (ms)",
            _q(one["task_delivery_ms"], "p50", "p95"),
            _q(two["task_delivery_ms"], "p50", "p95"),
        ),
        (
            "relayed round trip p50 / p95 (ms)",
            _q(relay["one"], "p50", "p95"),
            _q(relay["two"], "p50", "p95"),
        ),
        (
            "CPU of the process holding the agents (%)",
            f"{cpu('one', load, 'platform-1'):.0f}",
            f"{cpu('two', load, 'platform-1 (agents)'):.0f}",
        ),
        (
            "CPU of the process serving users (%)",
            "(the same)",
            f"{cpu('two', load, 'platform-2 (users)'):.0f}",
        ),
        (
            "CPU of the whole machine (% of one core)",
            f"{cpu('one', load, 'whole machine'):.0f}",
            f"{cpu('two', load, 'whole machine'):.0f}",
        ),
    ]
    add("| under the same load | one process | two processes |")
    add("|---|---:|---:|")
    for row in rows:
        add(f"| {row[0]} | {row[1]} | {row[2]} |")
    add("")
    cores = int(m.get("cores") or 1)
    add(
        f"What the second process adds on this {cores}-core machine: sessions per second "
        f"{_change(one['sessions_per_s'], two['sessions_per_s'])}; request p95 (ms) "
        f"{_change(one['request_ms']['p95'], two['request_ms']['p95'])}; relayed round trip "
        f"p95 (ms) {_change(relay['one']['p95'], relay['two']['p95'])}. The whole machine ran "
        f"at {cpu('two', load, 'whole machine'):.0f} % of {100 * cores} % during the "
        "two-process load, load generators included."
    )
    add("")
    return _report_end(results, data, lines)


def _report_topology(results: Results, data: dict[str, Any], lines: list[str]) -> None:
    """The sections every topology has: CPU per role, the login flood, the fleet."""
    p = results.params
    add = lines.append
    roles = data.get("roles") or {}
    if roles:
        add("## CPU per role")
        add("")
        add(
            "Percent of one core over each window, each role's processes summed (gunicorn: "
            "its masters and workers; Celery: the worker with its threads and the beat)."
        )
        add("")
        names = sorted({r for by in roles.values() for r in by}, key=_role_order)
        add("| window | " + " | ".join(names) + " |")
        add("|---|" + "---:|" * len(names))
        for phase, by in roles.items():
            add(
                f"| {phase} | "
                + " | ".join(f"{by[n]:.1f}" if n in by else "" for n in names)
                + " |"
            )
        add("")
    flood = data.get("flood")
    if flood:
        add("## 5. Login flood")
        add("")
        add(
            f"{_api_load(p)}, each turn reading the catalogue (`GET /api/v1/services`) "
            "before requesting and ending a session: "
            f"{p.flood_duration_s:g} s alone, then {p.flood_duration_s:g} s while "
            f"{flood['clients']} clients, each from its own address, posted wrong passwords "
            "to `/accounts/login/` as fast as they were answered (the CSRF token read "
            f"once): {flood['attempts']} attempts ({flood['attempts_per_s']:.1f}/s, "
            f"answered in p50 / p95 {_q(flood['attempt_ms'], 'p50', 'p95')} ms)."
        )
        add("")
        add("| API (ms) | without the flood | during the flood |")
        add("|---|---:|---:|")
        for label, key in (
            ("`GET /api/v1/services` p50 / p95", "services_ms"),
            ("session request p50 / p95", "request_ms"),
            ("session end p50 / p95", "end_ms"),
            ("every API call p50 / p95 / max", "all_ms"),
        ):
            keys = ("p50", "p95", "max") if key == "all_ms" else ("p50", "p95")
            add(
                f"| {label} | {_q(flood['api']['without'][key], *keys)} | "
                f"{_q(flood['api']['during'][key], *keys)} |"
            )
        add(
            "| sessions per s | "
            + " | ".join(f"{flood['api'][w]['sessions_per_s']:.1f}" for w in FLOOD_WINDOWS)
            + " |"
        )
        add(
            "| answers | "
            + " | ".join(
                ", ".join(f"{k}: {v}" for k, v in sorted(flood["api"][w]["statuses"].items()))
                for w in FLOOD_WINDOWS
            )
            + " |"
        )
        add("")
        add(
            "What the flood's attempts were answered (status, and who answered a 429: "
            "nginx's `limit_req` on the login, or the platform's lockout, django-axes): "
            + ", ".join(f"{k}: {v}" for k, v in sorted(flood["answers"].items()))
            + "."
        )
        add("")
    fleet = data.get("fleet_phase")
    if fleet:
        add(f"## 6. The fleet at {fleet['agents']} agents")
        add("")
        add(
            f"After the phases above, the fleet grew to {fleet['agents']} light agents "
            f"(heartbeat every {results.machine.get('heartbeat_s')} s): online at least "
            f"**{fleet['online_min']} of {fleet['agents']}** over the window (mean "
            f"{fleet['online_mean']:.0f}), the platform's processes at "
            f"{fleet['cpu_pct']:.0f} % of one core, {fleet['heartbeats_per_s']:.0f} "
            f"heartbeats/s sent, **{_ms(fleet['cpu_ms_per_heartbeat'])} ms of CPU per "
            "heartbeat** (all of the serving processes' CPU, an upper bound)."
        )
        add("")


def _role_order(name: str) -> tuple[int, str]:
    order = ("platform", "nginx", "celery", "whole machine")
    return next((i for i, o in enumerate(order) if name.startswith(o)), len(order)), name


def _report_end(results: Results, data: dict[str, Any], lines: list[str]) -> str:
    """The report's closing sections (per role, the flood, the fleet, the platform's
    logs, the run's notes), joined."""
    p = results.params
    _report_topology(results, data, lines)
    add = lines.append
    if results.log_counts:
        add("## What the platform processes logged")
        add("")
        names = list(results.log_counts)
        add("| | " + " | ".join(names) + " |")
        add("|---|" + "---:|" * len(names))
        for label in LOG_PATTERNS:
            add(
                f"| {label} | "
                + " | ".join(str(results.log_counts[n][label]) for n in names)
                + " |"
            )
        add("")
        add(
            f"Process 1 holds the uplinks in both topologies; each of the "
            f"{p.light_agents + p.cars_needed} agents opens one uplink per phase (two phases), so "
            "more accepted uplinks than that are reconnections."
            if p.two_processes
            else f"Each of the {p.light_agents + p.cars_needed} agents opened one uplink; "
            "more accepted uplinks than that are reconnections (production: spread over "
            "the uvicorn processes)."
        )
        add("")
    if results.notes:
        add("## Notes from the run")
        add("")
        counts: dict[str, int] = {}
        for note in results.notes:
            counts[note] = counts.get(note, 0) + 1
        for note, count in counts.items():
            add(f"* {note}" + (f" ({count} times)" if count > 1 else ""))
        add("")
    return "\n".join(lines)


# ======================================================================================
# Command line
# ======================================================================================


@dataclass(frozen=True)
class Variant:
    """One run of a comparison: a platform tree under one server in one topology,
    written to ``folder`` (relative to ``--out``; empty for a single run, written to
    ``--out`` itself)."""

    label: str
    tree: PlatformTree
    server: str
    folder: str
    topology: str = "single"


#: A single run's outputs: removed from ``--out`` when a comparison writes its own
#: report there, so no stale single-run file sits beside it.
SINGLE_RUN_FILES = (
    "resources.csv",
    "api_requests.csv",
    "task_delivery.csv",
    "relay_rtt.csv",
    "reaction_trials.csv",
    "login_flood.csv",
    "flood_api_requests.csv",
)


def variants(
    trees: Sequence[PlatformTree],
    servers: Sequence[str],
    topologies: Sequence[str] = ("single",),
) -> list[Variant]:
    """Every tree under every server in every topology (the production shape under
    uvicorn only), the baseline's runs first; labels "before" and "after" when there
    are two trees, the server's name when there are two servers, the topology's when
    there are two topologies."""
    combos = [
        (tree, server, topology)
        for tree in trees
        for server in servers
        for topology in topologies
        if topology == "single" or server == "uvicorn"
    ]
    out = []
    for tree, server, topology in combos:
        words = []
        if len(trees) > 1:
            words.append("before" if tree.commit else "after")
        if len(servers) > 1:
            words.append(server)
        if len(topologies) > 1:
            words.append(topology)
        if not words:
            words.append(server)
        label = " ".join(words)
        folder = "" if len(combos) == 1 else label.replace(" ", "-")
        out.append(Variant(label, tree, server, folder, topology))
    return out


def _stopped(signum: int, frame: Any) -> None:
    raise asyncio.CancelledError


def run_variants(
    params: Params,
    *,
    baseline: str | None,
    servers: Sequence[str],
    out: Path,
    command: str,
    database_url: str,
    topologies: Sequence[str] = ("single",),
) -> None:
    """Run ``params`` against each variant in turn (see :func:`variants`), each on a
    database prepared by its own tree (dropped first when a baseline is compared: a
    tree's migrations cannot undo a newer tree's). With more than one variant, each
    run's outputs go to a folder of its own and ``out/report.md`` puts them side by
    side (``out/summary.json`` lists them)."""
    with contextlib.ExitStack() as stack:
        trees = [PlatformTree()]
        if baseline:
            trees.insert(0, stack.enter_context(worktree(baseline)))
        runs = variants(trees, servers, topologies)
        done: list[tuple[str, str, dict[str, Any]]] = []
        for v in runs:
            # Between runs (asyncio's handler is gone once a run's loop is closed), SIGTERM
            # unwinds this stack too, so the baseline's worktree is removed.
            signal.signal(signal.SIGTERM, _stopped)
            print(
                f"benchmarks.scale: {v.label or 'run'}: {v.tree.label} under {v.server}, "
                f"topology {v.topology}",
                flush=True,
            )
            database_create(database_url, fresh=bool(baseline))
            where = out / v.folder if v.folder else out
            run(
                replace(params, server=v.server, topology=v.topology),
                out=where,
                command=command,
                database_url=database_url,
                tree=v.tree,
                prepare=True,
            )
            done.append((v.label, v.folder, json.loads((where / "summary.json").read_text())))
    if len(runs) == 1:
        print((out / "report.md").read_text().split("## Machine")[0])
        return
    for name in SINGLE_RUN_FILES:
        (out / name).unlink(missing_ok=True)
    (out / "summary.json").write_text(
        json.dumps(
            {"command": command, "runs": [{"label": lb, "folder": f} for lb, f, _ in done]},
            indent=2,
        )
        + "\n"
    )
    report = compare_md(done, command=command)
    (out / "report.md").write_text(report)
    print(report)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.scale",
        description="Agents, assignment and deployment, link loss, one vs two platform processes.",
    )
    parser.add_argument("--quick", action="store_true", help="the smoke test: small and short")
    parser.add_argument("--agents", type=int, help="light agents (default 1000; quick: 50)")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks" / "scale")
    parser.add_argument("--agent-workers", type=int, help="processes running the light agents")
    parser.add_argument("--ramp", type=float, help="new uplinks per second (default 50)")
    parser.add_argument("--window", type=float, help="CPU/memory window, seconds")
    parser.add_argument("--api-clients", type=int, help="concurrent API clients")
    parser.add_argument("--api-duration", type=float, help="seconds of API load per topology")
    parser.add_argument(
        "--api-rate",
        type=float,
        help="sessions started per second by the API clients together, evenly paced "
        "(default 0: a closed loop, each client's next session as soon as its last ended)",
    )
    parser.add_argument("--trials", type=int, help="link-loss trials per case and topology")
    parser.add_argument(
        "--heartbeat-s",
        type=float,
        help="the platform's IOUV_HEARTBEAT_INTERVAL_S (default: its own, 2 s); "
        "IOUV_OFFLINE_AFTER_S is set to three times it",
    )
    parser.add_argument(
        "--phases",
        choices=PHASES,
        default="all",
        help="heartbeats: phase 1 only (agents connected, no cars, no API load); one: "
        "phases 1-3 (one platform process); all (default): 1-4",
    )
    shapes = parser.add_mutually_exclusive_group()
    shapes.add_argument(
        "--topology",
        choices=TOPOLOGIES,
        default="single",
        help="single (default): one platform process serving everything behind nginx; "
        "production: deploy/'s shape, gunicorn for HTTP and uvicorn for WebSockets behind "
        "nginx (benchmarks.scale_topology)",
    )
    shapes.add_argument(
        "--topologies",
        help="comma list, e.g. single,production: the whole run in each, one after the "
        "other, reported side by side (the paired run)",
    )
    parser.add_argument("--web", type=int, help="production: gunicorn instances (default 1)")
    parser.add_argument(
        "--web-workers", type=int, help="production: workers per gunicorn instance (default 2)"
    )
    parser.add_argument(
        "--web-threads", type=int, help="production: threads per gunicorn worker (default 4)"
    )
    parser.add_argument("--ws", type=int, help="production: uvicorn processes (default 2)")
    parser.add_argument(
        "--flood-clients",
        type=int,
        help="login flood clients, each from its own address (default 4; 0: no flood phase)",
    )
    parser.add_argument(
        "--flood-duration", type=float, help="seconds of each login-flood window (default 20)"
    )
    parser.add_argument(
        "--fleet-agents",
        type=int,
        help="after the API phases, grow the fleet to this many light agents and measure "
        "their heartbeats (default: no such phase)",
    )
    servers = parser.add_mutually_exclusive_group()
    servers.add_argument(
        "--server",
        choices=SERVERS,
        default=SERVERS[0],
        help="the ASGI server of the platform processes (default uvicorn, as iouv.serve runs it)",
    )
    servers.add_argument(
        "--servers",
        help="comma list, e.g. uvicorn,daphne: the whole run under each, one after the "
        "other, reported side by side",
    )
    parser.add_argument(
        "--baseline",
        metavar="REF",
        help="a git ref: run the platform of REF (a git worktree, same virtualenv, the "
        "database dropped and migrated by REF) first, then this checkout's, with the same "
        "parameters and load, and report them side by side",
    )
    parser.add_argument(
        "--database-url",
        default=DEFAULT_DATABASE_URL,
        help="the benchmark's own database (created, migrated and EMPTIED; dropped with "
        "--baseline)",
    )
    parser.add_argument("--agent-worker", help=argparse.SUPPRESS)
    parser.add_argument("--api-worker", help=argparse.SUPPRESS)
    parser.add_argument("--flood-worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.agent_worker:
        # Warnings too: every lost uplink says why, which is what a reconnection storm
        # needs explained.
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(message)s")
        asyncio.run(agent_worker(json.loads(Path(args.agent_worker).read_text())))
        return
    if args.api_worker:
        api_worker(args.api_worker)
        return
    if args.flood_worker:
        flood_worker(args.flood_worker)
        return

    server_list = args.servers.split(",") if args.servers else [args.server]
    for name in server_list:
        if name not in SERVERS:
            parser.error(f"--servers: {name!r} is not one of {', '.join(SERVERS)}")
    topology_list = args.topologies.split(",") if args.topologies else [args.topology]
    for name in topology_list:
        if name not in TOPOLOGIES:
            parser.error(f"--topologies: {name!r} is not one of {', '.join(TOPOLOGIES)}")
    params = Params.quick_mode() if args.quick else Params()
    overrides = {
        "agents": args.agents,
        "agent_workers": args.agent_workers,
        "ramp_per_s": args.ramp,
        "window_s": args.window,
        "api_clients": args.api_clients,
        "api_rate": args.api_rate,
        "api_duration_s": args.api_duration,
        "trials": args.trials,
        "phases": args.phases,
        "web": args.web,
        "web_workers": args.web_workers,
        "web_threads": args.web_threads,
        "ws": args.ws,
        "flood_clients": args.flood_clients,
        "flood_duration_s": args.flood_duration,
        "fleet_agents": args.fleet_agents,
    }
    params = replace(params, **{k: v for k, v in overrides.items() if v is not None})
    # The platform under test and this process share these; the database is ours alone.
    os.environ["DATABASE_URL"] = args.database_url
    os.environ.setdefault("REDIS_URL", DEFAULT_REDIS_URL)
    os.environ.setdefault("CHANNELS_PREFIX", "benchscale")
    os.environ.setdefault("IOUV_VAR_DIR", str(ROOT / "var" / "bench-scale"))
    os.environ.setdefault("IOUV_DEV_SECRETS", "1")
    os.environ.setdefault("SECURE_SSL_REDIRECT", "0")
    os.environ.setdefault("SECURE_COOKIES", "0")
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")
    os.environ.setdefault("LOG_LEVEL", "WARNING")
    if args.heartbeat_s:
        # The platform processes and the probe inherit them.
        os.environ["IOUV_HEARTBEAT_INTERVAL_S"] = f"{args.heartbeat_s:g}"
        os.environ["IOUV_OFFLINE_AFTER_S"] = f"{3 * args.heartbeat_s:g}"
    logging.basicConfig(
        level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    # The cars' fail-safes are the point of phase 3: their warnings are not news.
    logging.getLogger("agents").setLevel(logging.ERROR)
    command = "python -m benchmarks.scale " + " ".join(argv if argv is not None else sys.argv[1:])
    try:
        run_variants(
            params,
            baseline=args.baseline,
            servers=server_list,
            topologies=topology_list,
            out=args.out,
            command=command.strip(),
            database_url=args.database_url,
        )
    except asyncio.CancelledError:
        sys.exit("benchmarks.scale: stopped (SIGTERM); what it had started is stopped too")


if __name__ == "__main__":
    main()
