"""The demo world run for real by the integration tests: the demo seeded (every user's
password :data:`PASSWORD`), the platform under its server (and a Celery worker when a
kind's missions need one), and the demo vehicles' agents on their simulators, from the
configs ``demo_seed`` writes, online.

:func:`agents_online` is the one place that starts demo agents and waits until the
platform has them online, :func:`demo_running` the one that runs the demo around them;
the portal's worlds (tests.portal) and the kinds' end-to-end tests
(:func:`missions_running`) are built on them.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import email
import email.policy
from collections.abc import AsyncIterator, Callable, Iterable
from pathlib import Path
from typing import Any

from agents.config import AgentConfig
from agents.runtime import Agent
from fleet.models import Vehicle
from services.demo import agent_configs_write, demo_seed
from tests.servers import (
    agent_started,
    cancelled,
    celery_worker_process,
    db,
    platform_process,
    until,
)

#: Every demo user's password in the tests (``demo_seed(password=...)``).
PASSWORD = "demo-pass-for-tests"


#: The test worlds' cameras: a quarter of the demo's 640x480. The pages, the agents and
#: the platform do the same with a picture of any size, and on the suite's two cores
#: each stream then costs its agent (drawing, VP8) and Chromium (decoding) about a
#: third as much. The video tests (tests/agents/test_video*.py, the benchmarks) size
#: their own.
TEST_CAMERA: dict[str, int] = {"width": 320, "height": 240}


def demo_agent_config(path: Path, base: str) -> AgentConfig:
    """The agent of a demo config file against the platform at ``base``, with synthetic
    video (of its scene: the boat's is the sea; :data:`TEST_CAMERA`'s size) offered on
    loopback only (aioice would otherwise offer this machine's other addresses),
    reconnecting quickly."""
    config = AgentConfig.load(path)
    scene = (config.video or {}).get("scene", "land")
    return dataclasses.replace(
        config,
        platform_url=base.replace("http://", "ws://"),
        video={
            "source": "synthetic",
            "scene": scene,
            **TEST_CAMERA,
            "ice_host_addresses": ["127.0.0.1"],
        },
        reconnect_min_s=0.2,
    )


#: A drone's simulator on a mission: flying at 15 m/s, returning home at 20 m, at 20x;
#: a drone with a thermal camera at 10x, for its camera's ~9 frames a second (on the
#: wall clock) to see the sea every 17 m of a search (its footprint is about 30 m wide).
SIM: dict[str, Any] = {"speedup": 20, "params": {"WPNAV_SPEED": 1500, "RTL_ALT": 2000}}
SEARCH_SIM: dict[str, Any] = {**SIM, "speedup": 10}
#: The boat's simulator on a mission: ArduRover's own parameters, at 20x.
BOAT_SIM: dict[str, Any] = {"speedup": 20}


def mission_agent_config(path: Path, base: str, *, video: bool = False) -> AgentConfig:
    """The agent of a demo config file against the platform at ``base``, on its fast
    simulator (:data:`SIM`, :data:`SEARCH_SIM`, :data:`BOAT_SIM`), so that a mission
    takes seconds; with its camera's video offered on loopback if ``video`` (and it has
    a camera), else none."""
    config = AgentConfig.load(path)
    simulator = SEARCH_SIM if "thermal" in config.sensors else SIM
    if config.adapter_options.get("vehicle_class") == "boat":
        simulator = BOAT_SIM
    return dataclasses.replace(
        config,
        platform_url=base.replace("http://", "ws://"),
        adapter_options={**config.adapter_options, "simulator": simulator},
        video=(
            {**(config.video or {}), "ice_host_addresses": ["127.0.0.1"]}
            if video and config.video
            else None
        ),
        reconnect_min_s=0.2,
    )


@dataclasses.dataclass
class Agents:
    """Agents running on their simulators, by vehicle name, each in a task of its own."""

    agents: dict[str, Agent]
    tasks: dict[str, asyncio.Task[None]]

    async def switch_off(self, name: str) -> None:
        """Vehicle ``name`` and its agent stop at once, wherever they are."""
        await cancelled(self.tasks.pop(name))

    async def stop(self) -> None:
        for name in list(self.tasks):
            await self.switch_off(name)


@contextlib.asynccontextmanager
async def agents_online(
    configs: dict[str, AgentConfig], *, within: float, positioned: bool = True, what: str = ""
) -> AsyncIterator[Agents]:
    """Start the agent of each config (by vehicle name) on its simulator and wait, up to
    ``within`` seconds, until the platform has every one idle (``positioned``: with a
    position too: matching measures from where a vehicle reports it is, and a drone has
    none before its autopilot's GPS fix). Yields the :class:`Agents`; on exit those still
    running are switched off (the agent cancelled, then its simulator stopped)."""
    running = Agents({}, {})
    try:
        for name, config in configs.items():
            running.agents[name], running.tasks[name] = await agent_started(config)

        async def online() -> bool:
            ready = Vehicle.objects.filter(name__in=list(configs), status="idle")
            if positioned:
                ready = ready.filter(lat__isnull=False)
            return await db(ready.count) == len(configs)

        where = " with a position" if positioned else ""
        await until(online, within=within, what=what or f"{', '.join(configs)} online{where}")
        yield running
    finally:
        await running.stop()


def spare_vehicle(directory: Path, *, like: str, name: str) -> None:
    """Another vehicle ``name`` at the same station as the demo's ``like`` and the same
    as it, with its agent's config written into ``directory``."""
    spare = Vehicle.objects.get(name=like)
    spare.pk, spare.name, spare.credential_hash = None, name, ""
    spare.save()
    agent_configs_write(
        vehicles={name: spare}, directory=directory, platform_url="ws://127.0.0.1:1"
    )


@dataclasses.dataclass(kw_only=True)
class Demo(Agents):
    """The demo running: the platform at ``base``, the Celery ``worker`` (a handle of
    tests.servers.celery_worker_process; None when it runs none) and the agents. E-mail,
    when the settings write it to files (:func:`missions_running`), goes to
    ``mail_dir``."""

    base: str
    worker: Any
    mail_dir: Path

    def emails(self) -> list[str]:
        """The e-mails sent so far, as their reader sees them: each one's headers (one
        line each), a blank line, and its text decoded (Django 6 sends long lines
        quoted-printable, folded at 76 characters, which a mail client undoes). A file
        the backend had not finished (its writer killed while sending, as some tests do:
        the file is opened first, written and closed after) holds no e-mail sent, as a
        message cut off mid-way never reaches a mail server; Django's file backend ends
        every message it finished with a line of 79 dashes."""
        if not self.mail_dir.exists():
            return []
        end = "\n" + "-" * 79 + "\n"
        sent: list[str] = []
        for path in sorted(self.mail_dir.glob("*.log")):
            text = path.read_text()
            if text.endswith(end):
                sent += [_readable(raw) for raw in text.split(end) if raw.strip()]
        return sent


def _readable(raw: str) -> str:
    message = email.message_from_string(raw, policy=email.policy.default)
    headers = "".join(f"{name}: {value}\n" for name, value in message.items())
    body = message.get_body(preferencelist=("plain", "html"))
    return f"{headers}\n{body.get_content() if body is not None else ''}"


@contextlib.asynccontextmanager
async def demo_running(
    directory: Path,
    names: Iterable[str],
    configure: Callable[[Path, str], AgentConfig] = demo_agent_config,
    *,
    env: dict[str, str] | None = None,
    worker: bool = False,
    spares: dict[str, str] | None = None,
    within: float = 30,
    positioned: bool = True,
    what: str = "",
) -> AsyncIterator[Demo]:
    """The seeded demo (its agents' configs in ``directory``, with a spare vehicle of
    each ``spares`` name like the demo vehicle it maps to), the platform (and with
    ``worker`` a Celery worker with its beat; both with ``env`` added to the
    environment), and the agents of ``names`` online (see :func:`agents_online`): each
    one's config is ``configure(its config file, the platform's base URL)``."""
    await db(demo_seed, password=PASSWORD, credentials_dir=directory)
    for name, like in (spares or {}).items():
        await db(spare_vehicle, directory, like=like, name=name)
    with contextlib.ExitStack() as servers:
        base = servers.enter_context(platform_process(extra_env=env))
        handle = servers.enter_context(celery_worker_process(extra_env=env)) if worker else None
        configs = {name: configure(directory / f"{name}.json", base) for name in names}
        async with agents_online(
            configs, within=within, positioned=positioned, what=what
        ) as running:
            yield Demo(
                agents=running.agents,
                tasks=running.tasks,
                base=base,
                worker=handle,
                mail_dir=directory / "mail",
            )


def missions_running(
    directory: Path,
    names: Iterable[str],
    configure: Callable[[Path, str], AgentConfig],
    *,
    env: dict[str, str] | None = None,
    spares: dict[str, str] | None = None,
    what: str,
) -> contextlib.AbstractAsyncContextManager[Demo]:
    """:func:`demo_running` for a kind's missions: with the worker, the platform and
    the worker running a mission's loop every second, replacing a vehicle offline for
    3 s (its autopilot's own mission or not: the tests' vehicles go silent by being
    switched off, autopilot and all), handing a task a killed worker held to another
    after 5 s, and writing e-mail to files (``env`` adds to or overrides these); the
    agents online once idle, wherever they are."""
    mission_env = {
        "IOUV_MISSION_TICK_S": "1",
        "IOUV_MISSION_OFFLINE_GRACE_S": "3",
        "IOUV_MISSION_FLYING_ALONE_MAX_S": "0",
        "CELERY_VISIBILITY_TIMEOUT_S": "5",
        "EMAIL_BACKEND": "django.core.mail.backends.filebased.EmailBackend",
        "EMAIL_FILE_PATH": str(directory / "mail"),
        **(env or {}),
    }
    return demo_running(
        directory,
        names,
        configure,
        env=mission_env,
        worker=True,
        spares=spares,
        positioned=False,
        what=what,
    )
