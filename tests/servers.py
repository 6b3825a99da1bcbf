"""Real servers for integration tests: the platform under its server (``iouv.serve``:
uvicorn), or under daphne when a test asks, in its own process.

The child process uses the test database that pytest-django created (so the test must
commit its rows: ``django_db(transaction=True)``), the same Redis channel layer and
the same ``var/`` folder, hence the same platform signing key.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from collections.abc import AsyncIterator, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import redis
from asgiref.sync import sync_to_async
from django.conf import settings
from django.db import connections

from agents.config import AgentConfig, ControlConfig
from agents.runtime import Agent
from agents.simulation import simulator_running
from agents.vehicles.base import Simulation
from iouv.serve import APPLICATION
from iouv.serve import command as iouv_serve_command
from services.sessions.signing import platform_public_key_pem
from tests.ports import free_port as free_port  # what the tests import from here

ROOT = Path(__file__).resolve().parents[1]


def _test_database_url() -> str:
    db = settings.DATABASES["default"]
    user = db.get("USER") or ""
    password = f":{db['PASSWORD']}" if db.get("PASSWORD") else ""
    return (
        f"postgres://{user}{password}@{db.get('HOST') or '127.0.0.1'}:{db.get('PORT') or 5432}"
        f"/{db['NAME']}"
    )


#: The ASGI servers a test may run the platform under; the first is production's.
SERVERS = ("uvicorn", "daphne")


def server_command(server: str, *, host: str, port: int) -> list[str]:
    """The command line serving the platform under ``server`` (one of :data:`SERVERS`)."""
    if server == "uvicorn":
        return iouv_serve_command(host=host, port=port)
    if server == "daphne":
        return [sys.executable, "-m", "daphne", "-b", host, "-p", str(port), APPLICATION]
    raise ValueError(f"unknown server {server!r}; one of {', '.join(SERVERS)}")


def platform_log(base: str) -> Path:
    """The output file of the platform process serving ``base``."""
    return Path(settings.VAR_DIR / f"platform-{base.rsplit(':', 1)[1]}.log")


@contextlib.contextmanager
def platform_process(
    *,
    extra_env: dict[str, str] | None = None,
    host: str = "127.0.0.1",
    server: str = SERVERS[0],
) -> Iterator[str]:
    """Run the platform on a free port of ``host`` (default loopback) under ``server``
    (default production's, ``iouv.serve``); yields its base URL (``http://<host>:N``, or
    ``http://127.0.0.1:N`` when ``host`` is ``0.0.0.0``). Its output goes to
    :func:`platform_log`.

    Another address (e.g. the public address of a tests.netlab lab, for clients in its
    namespaces) is added to ``ALLOWED_HOSTS``, unless ``extra_env`` sets that; with
    ``0.0.0.0`` the names clients use are the caller's to allow there."""
    with platform_server(extra_env=extra_env, host=host, server=server) as platform:
        yield platform.base


@contextlib.contextmanager
def platform_server(
    *,
    extra_env: dict[str, str] | None = None,
    host: str = "127.0.0.1",
    server: str = SERVERS[0],
) -> Iterator[PlatformServer]:
    """:func:`platform_process`, yielding a handle that can also kill the platform
    (``kill``: SIGKILL, as a crash; ``terminate``: SIGTERM, as a deploy) and start it
    again on the same address (``start``)."""
    port = free_port(host)
    env = {
        **os.environ,
        "DATABASE_URL": _test_database_url(),
        "DB_CONN_MAX_AGE": "0",
        "PYTHONUNBUFFERED": "1",
        # Users made by the test are hashed with tests/conftest.py's fast hasher.
        "IOUV_FAST_PASSWORD_HASHER": "1",
        **(extra_env or {}),
    }
    url_host = "127.0.0.1" if host == "0.0.0.0" else host
    if url_host not in settings.ALLOWED_HOSTS and "ALLOWED_HOSTS" not in (extra_env or {}):
        env["ALLOWED_HOSTS"] = ",".join([*settings.ALLOWED_HOSTS, url_host])
    platform = PlatformServer(
        server_command(server, host=host, port=port),
        env=env,
        base=f"http://{url_host}:{port}",
        log_path=settings.VAR_DIR / f"platform-{port}.log",
    )
    try:
        platform.start()
        yield platform
    finally:
        platform.terminate()


class PlatformServer:
    """One platform process on a fixed address; see :func:`platform_server`."""

    def __init__(self, command: list[str], *, env: dict[str, str], base: str, log_path: Path):
        self.command = command
        self.env = env
        self.base = base
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self, within: float = 90.0) -> None:
        """Start the process and return once it answers ``/healthz``; RuntimeError if it
        exits first or has not answered ``within`` seconds. The bound is generous: a
        start is mostly imports, which take a minute of wall time on a machine whose
        cores are shared by a dozen busy processes (a loaded CI runner)."""
        self.starts += 1
        with open(self.log_path, "a") as log:  # the child keeps its own descriptor
            self.proc = subprocess.Popen(
                self.command, cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + within
        while True:
            try:
                with urllib.request.urlopen(f"{self.base}/healthz", timeout=1) as response:
                    if response.status == 200:
                        return
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the platform did not start: {self.log_path.read_text()[-2000:]}"
                    ) from None
                time.sleep(0.2)

    def kill(self) -> None:
        """SIGKILL: no goodbye to anyone, its sockets die with it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)

    def terminate(self) -> None:
        """SIGTERM, as a deploy stops it, then SIGKILL after 10 s."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)


@contextlib.contextmanager
def celery_worker_process(
    *, extra_env: dict[str, str] | None = None, extra_args: Sequence[str] = ()
) -> Iterator[Any]:
    """Run a Celery worker with its beat on the test database and Redis (``extra_args``
    added to its command line, e.g. ``--include`` a module of tasks); yields a handle
    whose ``kill()`` SIGKILLs the worker (as a crash would) and ``start()`` starts a
    fresh one."""
    env = {
        **os.environ,
        "DATABASE_URL": _test_database_url(),
        "DB_CONN_MAX_AGE": "0",
        "PYTHONUNBUFFERED": "1",
        **(extra_env or {}),
    }
    handle = _Worker(env, extra_args)
    handle.start()
    try:
        yield handle
    finally:
        handle.stop()


class _Worker:
    def __init__(self, env: dict[str, str], extra_args: Sequence[str] = ()) -> None:
        self.env = env
        self.extra_args = list(extra_args)
        self.proc: subprocess.Popen[bytes] | None = None
        self.runs = 0

    def start(self) -> None:
        self.runs += 1
        tag = f"{os.getpid()}-{self.runs}"
        self.log = open(settings.VAR_DIR / f"celery-{tag}.log", "w")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [
                sys.executable, "-m", "celery", "-A", "iouv", "worker", "--beat",
                "--loglevel", "INFO", "--concurrency", "2", "--without-gossip",
                "--without-mingle", "--schedule", str(settings.VAR_DIR / f"beat-{tag}"),
                *self.extra_args,
            ],
            cwd=ROOT,
            env=self.env,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # kill() takes the pool's children too
        )  # fmt: skip

    def kill(self) -> None:
        """SIGKILL the worker and its pool: tasks in progress are never acknowledged."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, 9)
            self.proc.wait(timeout=10)
        self.log.close()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, 15)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, 9)
                self.proc.wait(timeout=10)
        self.log.close()

    def alive(self) -> bool:
        """True while the worker's main process runs (its beat is one of its children)."""
        return self.proc is not None and self.proc.poll() is None

    def output(self) -> str:
        return Path(self.log.name).read_text()[-4000:]

    def tasks_in_flight(self) -> list[str]:
        """Names of the tasks the worker received and has not finished, read from its
        log (Celery writes "Task <name>[<id>] received", then one more line per id)."""
        running: dict[str, str] = {}
        for name, task_id, word in _TASK_LOG.findall(Path(self.log.name).read_text()):
            if word == "received":
                running[task_id] = name
            else:
                running.pop(task_id, None)
        return sorted(running.values())

    def quiet_for(self) -> float:
        """Seconds since the worker (or its beat) last wrote to its log."""
        return time.time() - Path(self.log.name).stat().st_mtime


_TASK_LOG = re.compile(r"Task (\S+)\[([0-9a-f-]+)\] (\w+)")


@contextlib.contextmanager
def redis_server_process() -> Iterator[RedisServer]:
    """Run a private redis-server on a free loopback port, for tests that take Redis
    away (the machine's shared one must stay up for everyone else); yields its handle.
    Skips the test when ``redis-server`` is not installed."""
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("needs redis-server")
    server = RedisServer(binary, free_port())
    server.start()
    try:
        yield server
    finally:
        server.kill()


class RedisServer:
    """A redis-server process that keeps nothing on disk, on a fixed port: ``kill()``
    is an outage (SIGKILL, as a crash or a lost host), ``start()`` its end."""

    def __init__(self, binary: str, port: int) -> None:
        self.binary = binary
        self.port = port
        self.url = f"redis://127.0.0.1:{port}/0"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, within: float = 10.0) -> None:
        """Start the server and return once it answers PING."""
        self.proc = subprocess.Popen(
            [
                self.binary, "--port", str(self.port), "--bind", "127.0.0.1",
                "--save", "", "--appendonly", "no", "--dir", str(settings.VAR_DIR),
                "--logfile", str(settings.VAR_DIR / f"redis-{self.port}.log"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        client = redis.Redis(host="127.0.0.1", port=self.port, socket_connect_timeout=1)
        deadline = time.monotonic() + within
        try:
            while True:
                try:
                    client.ping()
                    return
                except redis.ConnectionError:
                    if self.proc.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(f"redis-server did not start on {self.port}") from None
                    time.sleep(0.1)
        finally:
            client.close()

    def kill(self) -> None:
        """SIGKILL the server: clients see their connections reset, then refused."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)


@sync_to_async
def db(fn: Any, *args: Any, **kwargs: Any) -> Any:
    """Run ORM code off the event loop; its connection closes after, so the test
    database can be dropped at the end."""
    try:
        return fn(*args, **kwargs)
    finally:
        connections.close_all()


async def cancelled(task: asyncio.Task[Any] | None) -> None:
    """Cancel ``task`` and wait until it has ended, whatever it raised. Cancelled again
    each second: a cancel can be lost (Python 3.11's ``asyncio.wait_for`` swallows one
    that arrives as what it waits for finishes, in code we do not own), and a task
    looping around such a wait would otherwise run on, holding its test for good."""
    if task is None:
        return
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=1)
    if not task.cancelled():
        task.exception()  # retrieved: what stopped it is the caller's to check


async def until(predicate: Any, *, within: float = 10.0, what: str = "") -> Any:
    """Poll ``predicate`` (a coroutine function) until it returns something truthy."""
    for _ in range(int(within / 0.1)):
        value = await predicate()
        if value:
            return value
        await asyncio.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what or predicate}")


@contextlib.asynccontextmanager
async def agent_simulated(
    *, base: str, vehicle: Any, credential: str, adapter: str, options: dict[str, Any]
) -> AsyncIterator[tuple[Agent, Simulation]]:
    """Run ``vehicle``'s agent on its simulator (the integration's hook, as ``python -m
    agents sim fleet`` runs it) against the platform at ``base``; yields the agent and
    the simulation (``options`` are adapter options, the simulator's own under
    ``simulator``).

    The agent is cancelled on exit, and must end by that cancellation, not by an error;
    the simulator stops after it.
    """
    async with simulator_running(adapter, options) as simulation:
        config = AgentConfig(
            platform_url=base.replace("http", "ws"),
            vehicle_id=str(vehicle.pk),
            credential=credential,
            platform_public_key=await db(platform_public_key_pem),
            adapter=adapter,
            adapter_options=simulation.options,
            control=ControlConfig(host="127.0.0.1", port=0),
            name=vehicle.name,
        )
        agent = Agent(config)
        run = asyncio.create_task(agent.run())
        try:
            yield agent, simulation
        finally:
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run


async def agent_started(config: AgentConfig) -> tuple[Agent, asyncio.Task[None]]:
    """Start the agent of ``config`` on its simulator in a task of its own; returns the
    agent (once built) and the task. Cancelling the task stops the agent, then its
    simulator, as a vehicle that is switched off."""
    built: asyncio.Future[Agent] = asyncio.get_running_loop().create_future()

    async def run() -> None:
        async with simulator_running(config.adapter, config.adapter_options) as simulation:
            agent = Agent(dataclasses.replace(config, adapter_options=simulation.options))
            built.set_result(agent)
            await agent.run()

    task = asyncio.create_task(run())
    started: list[asyncio.Future[Any]] = [built, task]
    done, _ = await asyncio.wait(started, return_when=asyncio.FIRST_COMPLETED)
    if built not in done:
        task.result()  # the simulator did not start: raise why
    return built.result(), task


@contextlib.asynccontextmanager
async def agent_configured(config: AgentConfig) -> AsyncIterator[tuple[Agent, Simulation]]:
    """Run the agent of ``config`` on its simulator (the integration's hook, as ``python
    -m agents sim fleet`` runs it) until the block ends; yields the agent and the
    simulation. The agent is cancelled on exit, then the simulator stops."""
    async with simulator_running(config.adapter, config.adapter_options) as simulation:
        agent = Agent(dataclasses.replace(config, adapter_options=simulation.options))
        run = asyncio.create_task(agent.run())
        try:
            yield agent, simulation
        finally:
            run.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await run


@contextlib.asynccontextmanager
async def agent_running(
    *, base: str, vehicle: Any, credential: str, adapter: str, options: dict[str, Any]
) -> AsyncIterator[Agent]:
    """:func:`agent_simulated`, yielding the agent alone."""
    async with agent_simulated(
        base=base, vehicle=vehicle, credential=credential, adapter=adapter, options=options
    ) as (agent, _):
        yield agent


def postgres_terminate(where: str, params: Sequence[Any]) -> int:
    """End the PostgreSQL backends ``pg_stat_activity`` rows matching ``where`` (an SQL
    condition with ``%s`` placeholders for ``params``) from outside, as a restart or an
    idle timeout would; how many ended."""
    import psycopg  # PostgreSQL-only tests call this

    db = settings.DATABASES["default"]
    with psycopg.connect(
        host=db.get("HOST") or "127.0.0.1",
        port=db.get("PORT") or 5432,
        user=db.get("USER") or None,
        password=db.get("PASSWORD") or None,
        dbname="postgres",
        autocommit=True,
    ) as admin:
        rows = admin.execute(
            f"SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE {where}",
            list(params),
        ).fetchall()
    return sum(1 for (ended,) in rows if ended)
