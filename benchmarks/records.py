"""The flight record's size per hour, and what recording it costs the agent's CPU
(docs/records.md).

    python -m benchmarks.records                  # 30 minutes of flight, about 32 min
    python -m benchmarks.records --quick --out /tmp/records  # 12 s at 5 m, under a minute

Two quadcopters on the project's MAVLink simulator (``agents.simulation``, speedup 1: the
autopilot's streams, the GCS heartbeats and the recorder's 5 Hz sampling run at the
rates of a real flight), each driven by a whole agent (``agents.runtime.Agent``, its
control hub, uplink and adapter) in a process of its own, fly the same pattern side by
side over the same wall-clock window:

* ``recording``: the agent as it ships, its :class:`~agents.recording.FlightRecorder`
  wired by the runtime (the hub's commands and events, the adapter's raw MAVLink frames
  both ways into the tlog, the uplink's acks);
* ``baseline``: the same agent with no recorder at all (the hub gets a no-op sink, the
  adapter no raw hook, nothing samples, writes or uploads).

Both uplinks go to a local platform in this process: it answers ``hello``, sends each
agent its task, **acknowledges every record batch** (so batches are written to disk,
sent, acknowledged and deleted as in production) and counts what arrives. Each drone is
flown as the portal's controller page flies it, over the agent's own control socket:
telemetry subscribed at 4 Hz, a keepalive every 100 ms, pings answered; take-off, then
laps of a square (go_to_waypoint to each corner), a 5 s stick hold forward (the page's
repeated ``front`` after each ack, every 100 ms) and a quarter turn per lap, until the
time is up; then land, and the platform ends the task.

**Size.** Every ``record`` frame the platform receives: its bytes, its samples' bytes
(each sample's JSON) by kind, batches; per hour of the session (first to last sample).

**CPU**, two ways, over the same window (task accepted to the last batch acknowledged):
the agent process's CPU time (``/proc/<pid>/stat``: user + system, every thread) with
the recorder minus without it (the paired difference; each minute's difference too, to
show how much of it is noise), and the recorder's own functions' CPU time in the
recording agent (``time.thread_time`` around each entry point the agent calls: the raw
hook, commands, events, the sampler, batch writing, the upload pass, acks; nested calls
counted once; everything runs on the agent's event loop thread). The first misses the
recorder's share of the uplink's socket writes and garbage collection only in its noise;
the second misses them outright.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import csv
import dataclasses
import datetime
import functools
import json
import logging
import os
import platform
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import msgspec
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from agents.recording import NullRecorder

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "benchmarks" / "records"
CLK_TCK = os.sysconf("SC_CLK_TCK")
#: Where the drones take off (the campus of the simulator's default origin).
HOME = (40.6306, -8.6588)
#: The square's side, metres; the drones fly it at the autopilot's own speed.
SIDE_M = 150.0
#: The page's keepalive and stick repeat (static/js/controller.js: 100 ms), and its
#: telemetry subscription (TELEMETRY_HZ).
KEEPALIVE_S = 0.1
STICK_REPEAT_S = 0.1
TELEMETRY_HZ = 4
#: A 30-minute flight on the simulator's default drain (5 %/min at full effort) would
#: end in a low-battery return; this drain leaves about half the battery.
DRAIN_PCT_PER_MIN = 1.5
#: How often the agents' CPU is read (and the minutes the paired difference is over).
SAMPLE_S = 10.0
ROLES = ("recording", "baseline")
COMMANDS = ("take_off", "go_to_waypoint", "front", "rotate_right", "land", "return_to_home")
TOPICS = ["altitude", "location", "heading", "flight_mode", "is_armed", "speed", "battery_level"]
KINDS = ("telemetry", "command", "event", "tlog", "dropped")

log = logging.getLogger("benchmarks.records")


@dataclasses.dataclass(frozen=True)
class Params:
    minutes: float = 30.0
    altitude_m: float = 30.0

    @property
    def seconds(self) -> float:
        return self.minutes * 60


# --------------------------------------------------------------------------------------
# The agent's side: one process per agent
# --------------------------------------------------------------------------------------


class CpuLedger:
    """CPU time (``time.thread_time``) spent inside the recorder's entry points, by
    label. A call from inside another timed call is not counted again. The agent calls
    the recorder from its event loop thread only, so thread time is the recorder's."""

    def __init__(self) -> None:
        self.seconds: Counter[str] = Counter()
        self.calls: Counter[str] = Counter()
        self._depth = 0

    def wrap(self, owner: Any, name: str, label: str) -> None:
        """Replace ``owner.name`` (a bound method) by a timed one, on the instance."""
        inner = getattr(owner, name)

        @functools.wraps(inner)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if self._depth:
                return inner(*args, **kwargs)
            self._depth += 1
            start = time.thread_time()
            try:
                return inner(*args, **kwargs)
            finally:
                self.seconds[label] += time.thread_time() - start
                self.calls[label] += 1
                self._depth -= 1

        setattr(owner, name, timed)

    def instrument(self, agent: Any) -> None:
        """Time every way into the agent's recorder (see the module docstring)."""
        recorder = agent.recorder
        for name, label in (
            ("raw", "raw"),
            ("command", "command"),
            ("event", "event"),
            ("session_start", "session"),
            ("session_end", "session"),
            ("_moving", "sampling"),
            ("_sample_telemetry", "sampling"),
            ("flush", "batches"),
            ("acked", "acked"),
        ):
            self.wrap(recorder, name, label)
        self.wrap(recorder.outbox, "upload", "upload")
        # The runtime handed the adapter the unwrapped bound method.
        agent.adapter.on_raw = recorder.raw

    @staticmethod
    def overhead_s_per_call(n: int = 200_000) -> float:
        """What the timing itself costs a call (a timed no-op less a plain one)."""
        ledger = CpuLedger()

        class Probe:
            def noop(self) -> None:
                return None

        plain, timed = Probe(), Probe()
        ledger.wrap(timed, "noop", "probe")
        runs = []
        for probe in (plain, timed):
            start = time.thread_time()
            for _ in range(n):
                probe.noop()
            runs.append(time.thread_time() - start)
        return max(0.0, (runs[1] - runs[0]) / n)


class _NoRecord(NullRecorder):
    """The baseline agent's recorder: keeps nothing, samples nothing, uploads nothing
    (agents.recording.NullRecorder, with what the agent's runtime also asks of the
    recorder it holds: the uplink slot, the context and the acks)."""

    uplink: Any = None

    async def __aenter__(self) -> _NoRecord:
        return self

    async def __aexit__(self, *exc: object) -> None:
        return None

    def acked(self, ack: Any) -> bool:
        return False


async def agent_process(spec: dict[str, Any]) -> None:
    """One agent on its own simulator (``spec``: see :func:`_agent_spec`); prints
    ``READY <control url> <simulator pid>``; on SIGTERM writes the ledger (recording)."""
    from agents.config import AgentConfig, ControlConfig, RecordsConfig
    from agents.runtime import Agent
    from agents.simulation import simulator_running

    options = {
        "origin": list(HOME),
        "simulator": {"speedup": 1, "drain_pct_per_min": DRAIN_PCT_PER_MIN},
    }
    async with simulator_running("mavlink", options) as simulation:
        config = AgentConfig(
            platform_url=spec["platform_url"],
            vehicle_id=spec["vehicle_id"],
            credential="benchmark",
            platform_public_key=spec["public_pem"],
            adapter="mavlink",
            adapter_options=simulation.options,
            control=ControlConfig(host="127.0.0.1", port=0),
            name=spec["vehicle_id"],
            records=RecordsConfig(directory=Path(spec["records_dir"])),
        )
        agent = Agent(config)
        ledger = CpuLedger()
        if spec["record"]:
            ledger.instrument(agent)
        else:
            agent.recorder = _NoRecord()  # type: ignore[assignment]
            agent.adapter.on_raw = None
        run = asyncio.create_task(agent.run())
        try:
            await asyncio.wait_for(agent.ready.wait(), 60)
            print("READY", agent.control_url, simulation.simulator.pid, flush=True)
            await run
        finally:
            run.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await run
            if spec["record"]:
                _ledger_write(Path(spec["ledger"]), ledger)


def _ledger_write(path: Path, ledger: CpuLedger) -> None:
    body = {
        "seconds": dict(ledger.seconds),
        "calls": dict(ledger.calls),
        "overhead_s_per_call": CpuLedger.overhead_s_per_call(),
    }
    path.write_text(json.dumps(body))


def _agent_main(spec_path: str) -> int:
    from agents.runtime import run_until_stopped

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    spec = json.loads(Path(spec_path).read_text())
    run_until_stopped(lambda: agent_process(spec))
    return 0


# --------------------------------------------------------------------------------------
# The platform's side: tasks, acks, counts
# --------------------------------------------------------------------------------------


@dataclasses.dataclass
class Received:
    """What one agent's uplink brought."""

    ws: ServerConnection | None = None
    registered: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)
    accepted: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)
    ended: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)
    last_record: float = 0.0
    frames: int = 0
    frame_bytes: int = 0
    batch_ids: set[str] = dataclasses.field(default_factory=set)
    samples: Counter[str] = dataclasses.field(default_factory=Counter)
    sample_bytes: Counter[str] = dataclasses.field(default_factory=Counter)
    tlog_raw_bytes: int = 0
    tlog_messages: int = 0
    first_t: float | None = None
    last_t: float | None = None
    seqs: int = 0
    events: Counter[str] = dataclasses.field(default_factory=Counter)
    deflate: Any = dataclasses.field(default_factory=lambda: zlib.compressobj(6))
    deflated: int = 0

    def record(self, raw: bytes, msg: dict[str, Any]) -> None:
        self.frames += 1
        self.frame_bytes += len(raw)
        self.deflated += len(self.deflate.compress(raw))
        self.last_record = time.monotonic()
        if msg["id"] in self.batch_ids:
            return  # sent again (no ack in time): counted as a frame, not as samples
        self.batch_ids.add(msg["id"])
        for sample in msg["samples"]:
            kind = sample["kind"]
            self.seqs += 1
            self.samples[kind] += 1
            self.sample_bytes[kind] += len(msgspec.json.encode(sample))
            t = float(sample["t"])
            self.first_t = t if self.first_t is None else min(self.first_t, t)
            self.last_t = t if self.last_t is None else max(self.last_t, t)
            if kind == "tlog":
                chunk = base64.b64decode(sample["data"]["b64"])
                self.tlog_raw_bytes += len(chunk)
                self.tlog_messages += tlog_messages(chunk)


def tlog_messages(chunk: bytes) -> int:
    """MAVLink messages in a tlog piece (each behind its 8-byte timestamp; v2 frames:
    10 bytes of header, 2 of checksum, 13 of signature when flagged; v1: 6 and 2)."""
    n, i = 0, 0
    while i + 9 < len(chunk):
        magic, length = chunk[i + 8], chunk[i + 9]
        if magic == 0xFD:
            size = 12 + length + (13 if chunk[i + 10] & 1 else 0)
        elif magic == 0xFE:
            size = 8 + length
        else:
            break
        i += 8 + size
        n += 1
    return n


class LocalPlatform:
    """Enough of the platform for two agents: welcome, the task, acks for every record
    batch, and counts of what came (:class:`Received`, by vehicle)."""

    def __init__(self, tasks: dict[str, str]) -> None:
        from agents.protocol import PROTOCOL_VERSION

        self.version = PROTOCOL_VERSION
        self.tasks = tasks
        self.received = {vehicle: Received() for vehicle in tasks}

    async def handle(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        side = self.received[hello["vehicle_id"]]
        await ws.send(
            json.dumps({"type": "welcome", "v": self.version, "heartbeat_interval_s": 2.0})
        )
        side.ws = ws
        with contextlib.suppress(Exception):
            async for frame in ws:
                raw = frame.encode() if isinstance(frame, str) else frame
                msg = json.loads(raw)
                kind = msg["type"]
                if kind == "profile" and not side.registered.is_set():
                    side.registered.set()
                    await ws.send(
                        json.dumps({"type": "task", "token": self.tasks[hello["vehicle_id"]]})
                    )
                elif kind == "task_accepted":
                    side.accepted.set()
                elif kind == "event":
                    side.events[msg["event"]] += 1
                    if msg["event"] == "task_ended":
                        side.ended.set()
                elif kind == "record":
                    side.record(raw, msg)
                    await ws.send(json.dumps({"type": "ack", "id": msg["id"], "ok": True}))

    async def end(self, vehicle: str, session: str) -> None:
        ws = self.received[vehicle].ws
        assert ws is not None
        await ws.send(json.dumps({"type": "end_task", "session_id": session, "reason": "flown"}))


# --------------------------------------------------------------------------------------
# The pilots
# --------------------------------------------------------------------------------------


class Pilot:
    """The portal's controller page on one agent's control socket (module docstring)."""

    def __init__(self, name: str, url: str, grant: str, params: Params) -> None:
        self.name, self.url, self.grant, self.params = name, url, grant, params
        self.telemetry: dict[str, Any] = {}
        self.seq = 0
        self.acks: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.sent: Counter[str] = Counter()
        self.refused: Counter[str] = Counter()
        self.laps = 0

    async def fly(self, deadline: float) -> None:
        async with connect(self.url, compression=None, proxy=None) as ws:
            await ws.send(json.dumps({"type": "auth", "grant": self.grant}))
            reader = asyncio.create_task(self._read(ws))
            keepalive = asyncio.create_task(self._keepalive(ws))
            try:
                await self._flight(ws, deadline)
            finally:
                for job in (keepalive, reader):
                    job.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await job

    async def _read(self, ws: ClientConnection) -> None:
        async for raw in ws:
            msg = json.loads(raw)
            kind = msg["type"]
            if kind == "welcome":
                topics = {"type": "subscribe", "topics": TOPICS, "rate_hz": TELEMETRY_HZ}
                await ws.send(json.dumps(topics))
            elif kind == "telemetry":
                self.telemetry.update(msg["data"])
            elif kind == "ping":
                await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))
            elif kind == "ack":
                future = self.acks.pop(msg["seq"], None)
                if future is not None and not future.done():
                    future.set_result(msg)

    async def _keepalive(self, ws: ClientConnection) -> None:
        while True:
            await asyncio.sleep(KEEPALIVE_S)
            await ws.send(json.dumps({"type": "keepalive"}))

    async def command(self, ws: ClientConnection, name: str, **args: Any) -> bool:
        self.seq += 1
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self.acks[self.seq] = future
        message = {"type": "command", "seq": self.seq, "name": name, "args": args}
        await ws.send(json.dumps(message))
        self.sent[name] += 1
        try:
            ack = await asyncio.wait_for(future, 10)
        except TimeoutError:
            self.acks.pop(self.seq, None)
            self.refused[f"{name}: no ack"] += 1
            return False
        if not ack["ok"]:
            self.refused[f"{name}: {ack.get('code') or ack.get('error')}"] += 1
        return bool(ack["ok"])

    async def until(self, check: Callable[[dict[str, Any]], bool], within: float) -> bool:
        end = time.monotonic() + within
        while time.monotonic() < end:
            if check(self.telemetry):
                return True
            await asyncio.sleep(0.1)
        return False

    def _near(self, point: tuple[float, float], metres: float) -> bool:
        from agents.geo import distance_m

        here = self.telemetry.get("location")
        return bool(here) and distance_m((here["lat"], here["lon"]), point) <= metres

    async def _flight(self, ws: ClientConnection, deadline: float) -> None:
        from agents.geo import offset

        alt = self.params.altitude_m
        if not await self.until(lambda t: t.get("location") and t.get("altitude") is not None, 60):
            raise RuntimeError(f"{self.name}: no position from the drone")
        await self.command(ws, "take_off", altitude_m=alt)
        await self.until(lambda t: (t.get("altitude") or 0) >= alt - 1, 120)
        corners = [
            offset(HOME, n, e) for n, e in ((SIDE_M, 0), (SIDE_M, SIDE_M), (0, SIDE_M), (0, 0))
        ]
        while time.monotonic() < deadline:
            for i, corner in enumerate(corners):
                if time.monotonic() >= deadline:
                    break
                await self.command(ws, "go_to_waypoint", lat=corner[0], lon=corner[1], alt_m=alt)
                within = max(0.0, min(120.0, deadline - time.monotonic()))
                await self.until(lambda t, c=corner: self._near(c, 4.0), within)
                if i == 1 and time.monotonic() < deadline:
                    await self._stick(ws, "front", 5.0, speed_mps=3)
                    await self.command(ws, "rotate_right", angle_deg=90)
            else:
                self.laps += 1
        await self.command(ws, "land")
        if not await self.until(lambda t: t.get("is_armed") is False, 180):
            log.warning("%s: not landed 180 s after land", self.name)

    async def _stick(self, ws: ClientConnection, name: str, seconds: float, **args: Any) -> None:
        """A stick held: the command again each time its ack came and the repeat passed."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            sent = time.monotonic()
            await self.command(ws, name, **args)
            await asyncio.sleep(max(0.0, STICK_REPEAT_S - (time.monotonic() - sent)))


# --------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (all its threads, not children)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


@dataclasses.dataclass
class AgentRun:
    role: str
    process: subprocess.Popen[str]
    control_url: str
    simulator_pid: int
    log_path: Path


def _agent_spec(role: str, tmp: Path, port: int, public_pem: str) -> Path:
    spec = {
        "vehicle_id": f"{role}-drone",
        "platform_url": f"ws://127.0.0.1:{port}",
        "public_pem": public_pem,
        "record": role == "recording",
        "records_dir": str(tmp / role / "records"),
        "ledger": str(tmp / role / "ledger.json"),
    }
    (tmp / role).mkdir(parents=True, exist_ok=True)
    path = tmp / role / "spec.json"
    path.write_text(json.dumps(spec))
    return path


async def _agent_start(role: str, tmp: Path, port: int, public_pem: str) -> AgentRun:
    spec = _agent_spec(role, tmp, port, public_pem)
    log_path = tmp / role / "agent.log"

    def spawn() -> subprocess.Popen[str]:
        with log_path.open("w") as stderr:
            return subprocess.Popen(
                [sys.executable, "-m", "benchmarks.records", "--agent-spec", str(spec)],
                cwd=ROOT,
                stdout=subprocess.PIPE,
                stderr=stderr,
                text=True,
            )

    process = await asyncio.to_thread(spawn)
    assert process.stdout is not None
    line = ""
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(90):
            line = await asyncio.to_thread(process.stdout.readline)
    words = line.split()
    if not words or words[0] != "READY":
        process.kill()
        tail = (await asyncio.to_thread(log_path.read_text))[-2000:]
        raise RuntimeError(f"the {role} agent did not start: {tail}")
    return AgentRun(role, process, words[1], int(words[2]), log_path)


async def _wait_for(done: Callable[[], bool], *, within: float) -> None:
    """Check ``done`` every 0.2 s until it holds; TimeoutError after ``within`` s."""
    for _ in range(int(within / 0.2)):
        if done():
            return
        await asyncio.sleep(0.2)
    raise TimeoutError(f"not done within {within} s")


def _stop(agent: AgentRun) -> None:
    if agent.process.poll() is None:
        agent.process.send_signal(signal.SIGTERM)
        try:
            agent.process.wait(30)
        except subprocess.TimeoutExpired:
            agent.process.kill()
            agent.process.wait()


@dataclasses.dataclass(frozen=True)
class Documents:
    """The platform's key, and each drone's session, as the platform would sign them."""

    public_pem: str
    key: Any
    sessions: dict[str, str]

    @classmethod
    def make(cls) -> Documents:
        from agents.protocol import generate_keypair, load_private_key

        private_pem, public_pem = generate_keypair()
        sessions = {f"{role}-drone": f"records-{role}" for role in ROLES}
        return cls(public_pem, load_private_key(private_pem), sessions)

    def task(self, vehicle: str, seconds: float) -> str:
        """The drone's task: the pilot's commands, a 60 m ceiling, RTL on link loss."""
        from agents.protocol import Limits, VehicleTask, new_nonce

        now = time.time()
        return VehicleTask(
            session_id=self.sessions[vehicle],
            vehicle_id=vehicle,
            user="pilot",
            allowed_commands=COMMANDS,
            limits=Limits(
                max_altitude_m=60, failsafe_action="return_to_home", link_loss_timeout_ms=2000
            ),
            issued_at=now,
            expires_at=now + seconds + 3600,
            nonce=new_nonce(),
        ).sign(self.key)

    def grant(self, vehicle: str) -> str:
        """The pilot's controller grant on the drone (checked when the pilot connects)."""
        from agents.protocol import UserGrant, new_nonce

        now = time.time()
        return UserGrant(
            session_id=self.sessions[vehicle],
            vehicle_id=vehicle,
            user="pilot",
            role="controller",
            allowed_commands=COMMANDS,
            issued_at=now - 1,
            expires_at=now + 600,
            nonce=new_nonce(),
        ).sign(self.key)


async def measure(params: Params, tmp: Path) -> dict[str, Any]:
    """Fly both drones (module docstring); returns the raw measurements."""
    documents = Documents.make()
    public_pem = documents.public_pem
    tasks = {vehicle: documents.task(vehicle, params.seconds) for vehicle in documents.sessions}
    platform_side = LocalPlatform(tasks)
    agents: dict[str, AgentRun] = {}
    samples: list[dict[str, float]] = []
    async with serve(platform_side.handle, "127.0.0.1", 0, max_size=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        try:
            started = await asyncio.gather(*(_agent_start(r, tmp, port, public_pem) for r in ROLES))
            agents = {a.role: a for a in started}
            got = {role: platform_side.received[f"{role}-drone"] for role in ROLES}
            async with asyncio.timeout(60):
                for side in got.values():
                    await side.accepted.wait()

            pids = {f"agent {r}": a.process.pid for r, a in agents.items()} | {
                f"simulator {r}": a.simulator_pid for r, a in agents.items()
            }
            pids["this process (platform, pilots)"] = os.getpid()
            t0 = time.monotonic()

            def snapshot() -> None:
                row = {"t_s": time.monotonic() - t0}
                for name, pid in pids.items():
                    with contextlib.suppress(OSError):
                        row[name] = cpu_s(pid)
                samples.append(row)

            async def sampler() -> None:
                while True:
                    snapshot()
                    await asyncio.sleep(SAMPLE_S)

            sampling = asyncio.create_task(sampler())
            deadline = time.monotonic() + params.seconds
            pilots = {
                role: Pilot(role, agent.control_url, documents.grant(f"{role}-drone"), params)
                for role, agent in agents.items()
            }
            await asyncio.gather(*(p.fly(deadline) for p in pilots.values()))
            flown_s = time.monotonic() - t0
            for vehicle, session in documents.sessions.items():
                await platform_side.end(vehicle, session)
            async with asyncio.timeout(60):
                for side in got.values():
                    await side.ended.wait()
            # The last batches: written at the session's end, then sent and acked.
            records_dir = tmp / "recording" / "records"
            await _wait_for(
                lambda: (
                    not list(records_dir.glob("*/batch-*.json"))
                    and time.monotonic() - got["recording"].last_record >= 2
                ),
                within=60,
            )
            sampling.cancel()
            snapshot()
            window_s = time.monotonic() - t0
            left = list(records_dir.glob("*/batch-*"))
        finally:
            for agent in agents.values():
                await asyncio.to_thread(_stop, agent)
    ledger = json.loads((tmp / "recording" / "ledger.json").read_text())
    logs = {
        role: [
            line
            for line in agent.log_path.read_text().splitlines()
            if (" WARNING " in line or " ERROR " in line or "Traceback" in line)
            # The benchmark's own SIGTERM at the end.
            and "SIGTERM: shutting down" not in line
        ]
        for role, agent in agents.items()
    }
    received = {role: got[role] for role in ROLES}
    for side in received.values():
        side.deflated += len(side.deflate.flush())
    return {
        "window_s": window_s,
        "flown_s": flown_s,
        "cpu_samples": samples,
        "received": received,
        "pilots": pilots,
        "ledger": ledger,
        "left_on_disk": len(left),
        "logs": logs,
    }


def _log_lines(lines: list[str], most: int = 20) -> list[str]:
    shown = [line.split(" ", 2)[-1] for line in lines[:most]]
    return shown + ([f"... {len(lines)} in all"] if len(lines) > most else [])


def _pct(seconds: float, window_s: float) -> float:
    return 100.0 * seconds / window_s if window_s > 0 else float("nan")


def figures(params: Params, m: dict[str, Any]) -> dict[str, Any]:
    """The report's figures from :func:`measure`'s measurements."""
    rec: Received = m["received"]["recording"]
    assert rec.first_t is not None and rec.last_t is not None
    session_s = max(rec.last_t - rec.first_t, 1e-9)
    per_h = 3600.0 / session_s
    total_sample_bytes = sum(rec.sample_bytes.values())
    by_kind = {
        kind: {
            "samples": rec.samples[kind],
            "samples_per_hour": rec.samples[kind] * per_h,
            "bytes": rec.sample_bytes[kind],
            "bytes_per_hour": rec.sample_bytes[kind] * per_h,
            "share": rec.sample_bytes[kind] / total_sample_bytes if total_sample_bytes else 0.0,
        }
        for kind in KINDS
    }
    samples = m["cpu_samples"]
    first, last = samples[0], samples[-1]
    window_s = last["t_s"] - first["t_s"]
    processes = {
        name: {
            "cpu_s": last[name] - first[name],
            "pct_of_one_core": _pct(last[name] - first[name], window_s),
        }
        for name in first
        if name != "t_s" and name in last
    }
    with_rec = processes["agent recording"]["cpu_s"]
    without = processes["agent baseline"]["cpu_s"]
    # The paired difference per stretch of SAMPLE_S x 6 (a minute): how steady it is.
    minute = max(1, round(60 / SAMPLE_S))
    diffs = []
    for i in range(0, len(samples) - minute, minute):
        a, b = samples[i], samples[i + minute]
        span = b["t_s"] - a["t_s"]
        diffs.append(
            _pct(
                (b["agent recording"] - a["agent recording"])
                - (b["agent baseline"] - a["agent baseline"]),
                span,
            )
        )
    ledger = m["ledger"]
    own = sum(ledger["seconds"].values())
    calls = sum(ledger["calls"].values())
    pilots: dict[str, Pilot] = m["pilots"]
    return {
        "params": dataclasses.asdict(params),
        "session_s": session_s,
        "flown_s": m["flown_s"],
        "window_s": window_s,
        "record": {
            "bytes": rec.frame_bytes,
            "bytes_per_hour": rec.frame_bytes * per_h,
            "deflated_bytes_per_hour": rec.deflated * per_h,
            "batches": len(rec.batch_ids),
            "batches_per_hour": len(rec.batch_ids) * per_h,
            "frames_sent_again": rec.frames - len(rec.batch_ids),
            "mean_batch_bytes": rec.frame_bytes / max(1, rec.frames),
            "samples": rec.seqs,
            "samples_per_hour": rec.seqs * per_h,
            "by_kind": by_kind,
            "tlog_raw_bytes_per_hour": rec.tlog_raw_bytes * per_h,
            "tlog_messages_per_s": rec.tlog_messages / session_s,
            "batches_left_on_disk": m["left_on_disk"],
        },
        "cpu": {
            "processes": processes,
            "recording_minus_baseline_s": with_rec - without,
            "recording_minus_baseline_pct_of_one_core": _pct(with_rec - without, window_s),
            "recording_minus_baseline_share": (with_rec - without) / without if without else None,
            "per_minute_difference_pct": {
                "n": len(diffs),
                "min": min(diffs) if diffs else None,
                "median": statistics.median(diffs) if diffs else None,
                "max": max(diffs) if diffs else None,
            },
            "recorder_own_s": own,
            "recorder_own_pct_of_one_core": _pct(own, window_s),
            "recorder_own_share_of_agent": own / with_rec if with_rec else None,
            "recorder_own_by_part": {
                label: {
                    "cpu_s": seconds,
                    "calls": ledger["calls"].get(label, 0),
                    "us_per_call": 1e6 * seconds / max(1, ledger["calls"].get(label, 0)),
                }
                for label, seconds in sorted(ledger["seconds"].items(), key=lambda kv: -kv[1])
            },
            "timing_overhead_s": calls * ledger["overhead_s_per_call"],
            "timing_overhead_us_per_call": 1e6 * ledger["overhead_s_per_call"],
        },
        "flight": {
            role: {
                "laps": p.laps,
                "commands": dict(p.sent),
                "not_ok": dict(p.refused),
            }
            for role, p in pilots.items()
        },
        "events": {role: dict(m["received"][role].events) for role in ROLES},
        # Warnings and errors the agents logged (up to 20 each, without their times).
        "agent_logs": {role: _log_lines(lines) for role, lines in m["logs"].items()},
    }


def machine() -> dict[str, Any]:
    cpu = platform.processor() or "unknown CPU"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    mem_gib = None
    with contextlib.suppress(OSError, IndexError, ValueError):
        kb = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        mem_gib = round(kb / 1024 / 1024)
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gib": mem_gib,
        "os": platform.platform(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def _mb(n: float) -> str:
    return f"{n / 1e6:.1f} MB"


def report(result: dict[str, Any]) -> str:
    """README.md: the command, the machine, the figures."""
    f, mach = result["figures"], result["machine"]
    r, c = f["record"], f["cpu"]
    procs = c["processes"]
    minutes = f["session_s"] / 60
    lines = [
        "# The flight record: size per hour, and the agent's CPU cost of recording",
        "",
        f"Regenerated with `{result['command']}` (benchmarks/records.py, whose docstring",
        "says how it flies and measures), on a machine shared with other work:",
        "",
        f"- CPU: {mach['cpu']}, {mach['cores']} logical cores"
        + (f", {mach['memory_gib']} GiB RAM" if mach["memory_gib"] else ""),
        f"- OS: {mach['os']}",
        f"- Python: {mach['python']}",
        f"- Date: {mach['date']}",
        "",
        f"Two quadcopters on the MAVLink simulator at speedup 1, each driven by a whole agent "
        f"in its own process, flew the same pattern side by side for {minutes:.1f} minutes "
        f"of session (take-off to {f['params']['altitude_m']:g} m, laps of a "
        f"{SIDE_M:.0f} m square by go_to_waypoint with a 5 s stick hold and a quarter turn "
        f"per lap, {f['flight']['recording']['laps']} laps, land), piloted as the portal's page "
        "does (4 Hz telemetry, a keepalive every 100 ms). One agent recorded its session "
        "with its FlightRecorder as the runtime wires it; the other had no recorder. A "
        "local platform acknowledged every batch, so batches were written, sent and "
        "deleted as in production.",
        "",
        "## Size",
        "",
        "| | per hour | in this run |",
        "|---|---|---|",
        f"| the record as uploaded (`record` frames) | **{_mb(r['bytes_per_hour'])}** "
        f"| {_mb(r['bytes'])} |",
        f"| the same frames deflated (zlib level 6, the zip export's compression) "
        f"| {_mb(r['deflated_bytes_per_hour'])} | |",
        f"| batches | {r['batches_per_hour']:,.0f} | {r['batches']:,} |",
        f"| samples | {r['samples_per_hour']:,.0f} | {r['samples']:,} |",
        f"| mean batch | {r['mean_batch_bytes'] / 1024:.1f} KiB | |",
        "",
        "By kind (each sample's JSON, without the batch's envelope):",
        "",
        "| kind | samples per hour | bytes per hour | share |",
        "|---|---|---|---|",
    ]
    for kind, k in r["by_kind"].items():
        if k["samples"] or kind != "dropped":
            lines.append(
                f"| `{kind}` | {k['samples_per_hour']:,.0f} | {_mb(k['bytes_per_hour'])} "
                f"| {100 * k['share']:.1f} % |"
            )
    lines += [
        "",
        f"The tlog carried {r['tlog_messages_per_s']:.1f} MAVLink messages a second, both "
        f"ways ({_mb(r['tlog_raw_bytes_per_hour'])} of raw `.tlog` an hour; base64 in its "
        f"samples makes it 4/3 of that). Batches left on the vehicle's disk at the end: "
        f"{r['batches_left_on_disk']}; frames sent again: {r['frames_sent_again']}.",
        "",
        "## CPU",
        "",
        f"Over the same {f['window_s'] / 60:.1f} minutes (task accepted to the last batch "
        "acknowledged), CPU time from `/proc/<pid>/stat` (user + system, all threads):",
        "",
        "| process | CPU s | % of one core |",
        "|---|---|---|",
    ]
    for name, p in procs.items():
        lines.append(f"| {name} | {p['cpu_s']:.1f} | {p['pct_of_one_core']:.2f} |")
    diff = c["per_minute_difference_pct"]
    share = c["recording_minus_baseline_share"]
    own_share = c["recorder_own_share_of_agent"]
    lines += [
        "",
        "| the cost of recording | CPU s | % of one core |",
        "|---|---|---|",
        f"| **agent with the recorder minus agent without** "
        f"| {c['recording_minus_baseline_s']:.1f} "
        f"| **{c['recording_minus_baseline_pct_of_one_core']:.2f}** |",
        f"| the recorder's own functions (thread CPU time, inside the recording agent) "
        f"| {c['recorder_own_s']:.1f} | **{c['recorder_own_pct_of_one_core']:.2f}** |",
        "",
        "The paired difference is "
        + (f"{100 * share:.0f} % of the baseline agent's CPU" if share is not None else "n/a")
        + "; the recorder's own functions are "
        + (f"{100 * own_share:.1f} % of the recording agent's" if own_share is not None else "n/a")
        + ". Minute by minute the paired difference was "
        + (
            f"{diff['min']:.2f} to {diff['max']:.2f} % of a core (median {diff['median']:.2f}, "
            f"{diff['n']} whole minutes)."
            if diff["n"]
            else "not measured (a run shorter than a minute)."
        ),
        "",
        "The recorder's own time by entry point:",
        "",
        "| part | CPU s | calls | µs per call |",
        "|---|---|---|---|",
    ]
    for label, part in c["recorder_own_by_part"].items():
        lines.append(
            f"| {label} | {part['cpu_s']:.2f} | {part['calls']:,} | {part['us_per_call']:.1f} |"
        )
    lines += [
        "",
        "`raw`: each MAVLink frame into the tlog buffer (and a tlog sample per 12 KiB); "
        "`sampling`: the 5 Hz telemetry sample; `batches`: the once-a-second batch "
        "(encoding, the file and its rename, `state.json`); `upload`: the outbox's pass "
        "(reading the file back, decoding it, encoding the frame); `acked`: deleting the "
        "file; `command`/`event`/`session`: those samples. The timing itself cost about "
        f"{c['timing_overhead_us_per_call']:.2f} µs a call ({c['timing_overhead_s']:.2f} s "
        "in all, inside the recording agent's figure).",
        "",
        "Commands each pilot sent (the same flight; `not_ok` are refusals or missing acks): "
        + "; ".join(
            f"{role}: {sum(fl['commands'].values())} sent, not ok {fl['not_ok'] or 'none'}"
            for role, fl in f["flight"].items()
        )
        + ". Warnings and errors in the agents' logs:",
        "",
        *(
            f"- {role}: " + ("; ".join(f"`{line}`" for line in lines) or "none")
            for role, lines in f["agent_logs"].items()
        ),
        "",
        f"All figures: `figures.json`; the CPU readings every {SAMPLE_S:.0f} s: `cpu.csv`.",
        "",
    ]
    return "\n".join(lines)


def write(out: Path, result: dict[str, Any]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "figures.json").write_text(
        json.dumps({k: result[k] for k in ("command", "machine", "figures")}, indent=1, default=str)
        + "\n"
    )
    samples = result["cpu_samples"]
    columns = list(samples[0])
    with (out / "cpu.csv").open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(columns)
        for row in samples:
            writer.writerow(f"{row.get(c, float('nan')):.2f}" for c in columns)
    (out / "README.md").write_text(report(result))


def run(params: Params, *, out: Path, command: str) -> dict[str, Any]:
    """Measure, write ``out``/README.md, figures.json and cpu.csv; returns the result."""
    with tempfile.TemporaryDirectory(prefix="iouv-records-") as tmp:
        measured = asyncio.run(measure(params, Path(tmp)))
    result = {
        "command": command,
        "machine": machine(),
        "figures": figures(params, measured),
        "cpu_samples": measured["cpu_samples"],
    }
    write(out, result)
    return result


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.records", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--minutes", type=float, default=Params.minutes, help="flight time")
    parser.add_argument("--altitude", type=float, default=Params.altitude_m, help="metres")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument(
        "--quick", action="store_true", help="the smoke: 12 s of flight at 5 m (--minutes 0.2)"
    )
    parser.add_argument("--agent-spec", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.agent_spec:
        return _agent_main(args.agent_spec)
    if args.quick:
        args.minutes, args.altitude = 0.2, 5.0
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    argv_used = list(sys.argv[1:] if argv is None else argv)
    command = shlex.join(["python", "-m", "benchmarks.records", *argv_used])
    run(Params(minutes=args.minutes, altitude_m=args.altitude), out=args.out, command=command)
    print((args.out / "README.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
