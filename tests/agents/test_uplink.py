"""The agent's uplink over a real socket, against a stand-in platform.

The platform sends what changes the vehicle's work with an ``id`` and repeats it until
acknowledged; the agent must handle each id once, acknowledge every delivery, and say
when handling failed. An uplink whose far end goes silent without closing (a platform
machine dropped off the network behind nginx) is given up by the agent's keepalive, and
the agent connects again.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection, serve

from agents.config import AgentConfig, ConfigError
from agents.protocol import PROTOCOL_VERSION
from agents.protocol.messages import Heartbeat, Profile, Revoke
from agents.uplink import CLOSE_TIMEOUT_S, PING_INTERVAL_S, PING_TIMEOUT_S, Uplink
from tests.agents.car_rig import PUBLIC_PEM

SESSION = "5b0d6c0e-8a3c-4d7e-9a51-0c4f1f2b7a10"
REVOKE = {"type": "revoke", "session_id": SESSION, "reason": "kill switch", "action": "land"}


class Platform:
    """Accepts one agent at a time: answers hello, then lets the test talk to it."""

    def __init__(self) -> None:
        self.connections: asyncio.Queue[ServerConnection] = asyncio.Queue()
        self.port = 0

    async def handler(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello"
        await ws.send(
            json.dumps({"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 30})
        )
        await self.connections.put(ws)
        await ws.wait_closed()


async def next_of(ws: ServerConnection, kind: str) -> dict[str, Any]:
    """The next message of ``kind`` from the agent (heartbeats and others skipped)."""
    while True:
        msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
        if msg["type"] == kind:
            return msg


def _uplink(port: int, on_message: Any, *, reconnect_max_s: float, **options: Any) -> Uplink:
    """An agent's uplink to the stand-in platform on ``port`` (``options``: Uplink's)."""
    return Uplink(
        url=f"ws://127.0.0.1:{port}/",
        vehicle_id="v-1",
        credential="c",
        on_message=on_message,
        profile=lambda: Profile(
            vehicle_type="car",
            adapter="sim",
            attributes={},
            commands=[],
            telemetry=[],
            control_url="",
            video=False,
            position=None,
            battery=None,
        ),
        heartbeat=lambda: Heartbeat(seq=0),
        reconnect_min_s=0.05,
        reconnect_max_s=reconnect_max_s,
        **options,
    )


@pytest.fixture
async def platform() -> AsyncIterator[Platform]:
    p = Platform()
    async with serve(p.handler, "127.0.0.1", 0) as server:
        p.port = next(iter(server.sockets)).getsockname()[1]
        yield p


@pytest.fixture
async def agent(platform: Platform) -> AsyncIterator[tuple[Uplink, list[Revoke]]]:
    handled: list[Revoke] = []

    async def on_message(msg: Revoke) -> None:
        handled.append(msg)
        if msg.reason == "explode":
            raise RuntimeError("the handler broke")

    uplink = _uplink(platform.port, on_message, reconnect_max_s=0.1)
    run = asyncio.create_task(uplink.run())
    yield uplink, handled
    run.cancel()
    with pytest.raises(asyncio.CancelledError):
        await run


async def test_a_message_with_an_id_is_handled_once_and_acknowledged_every_time(platform, agent):
    _uplink, handled = agent
    ws = await asyncio.wait_for(platform.connections.get(), 5)
    await ws.send(json.dumps({**REVOKE, "id": "m-1"}))
    assert await next_of(ws, "ack") == {"type": "ack", "id": "m-1", "ok": True, "detail": ""}
    # Resent (the platform did not hear the first ack): acknowledged, not handled again.
    await ws.send(json.dumps({**REVOKE, "id": "m-1"}))
    again = await next_of(ws, "ack")
    assert again["id"] == "m-1" and again["ok"] is True
    assert [m.id for m in handled] == ["m-1"]


async def test_a_handler_failure_is_acknowledged_as_failed(platform, agent):
    _uplink, handled = agent
    ws = await asyncio.wait_for(platform.connections.get(), 5)
    await ws.send(json.dumps({**REVOKE, "reason": "explode", "id": "m-2"}))
    ack = await next_of(ws, "ack")
    assert ack["id"] == "m-2" and ack["ok"] is False
    assert "the handler broke" in ack["detail"]
    # The uplink is still there for the next message.
    await ws.send(json.dumps({**REVOKE, "id": "m-3"}))
    assert (await next_of(ws, "ack"))["id"] == "m-3"
    assert len(handled) == 2


async def test_an_ack_the_link_lost_goes_out_on_the_next_connection(platform, agent):
    uplink, handled = agent
    ws = await asyncio.wait_for(platform.connections.get(), 5)
    # The message arrives and the link drops before anything else is said.
    handled_now = asyncio.Event()
    original = uplink.on_message

    async def slow(msg: Revoke) -> None:
        await original(msg)
        await ws.close()
        handled_now.set()

    uplink.on_message = slow
    await ws.send(json.dumps({**REVOKE, "id": "m-4"}))
    await asyncio.wait_for(handled_now.wait(), 5)
    uplink.on_message = original
    back = await asyncio.wait_for(platform.connections.get(), 5)
    assert (await next_of(back, "ack"))["id"] == "m-4"
    assert [m.id for m in handled] == ["m-4"]


async def test_an_agent_turned_away_as_busy_backs_off_and_comes_back(caplog) -> None:
    # Thousands of agents connecting at once: the platform turns some hellos away
    # ("busy", 4503); the agent waits its growing backoff and connects again, with no
    # error logged (nothing is wrong with it or the platform's messages).
    hellos: list[float] = []
    welcomed = asyncio.Event()

    async def handler(ws: ServerConnection) -> None:
        json.loads(await ws.recv())
        hellos.append(asyncio.get_running_loop().time())
        if len(hellos) <= 3:
            busy = {"type": "error", "code": "busy", "message": "try again later"}
            await ws.send(json.dumps(busy))
            await ws.close(4503, "busy")
            return
        await ws.send(
            json.dumps({"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 30})
        )
        welcomed.set()
        await ws.wait_closed()

    async with serve(handler, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        uplink = _uplink(port, lambda msg: asyncio.sleep(0), reconnect_max_s=5.0)
        with caplog.at_level("INFO", logger="agents.uplink"):
            run = asyncio.create_task(uplink.run())
            try:
                await asyncio.wait_for(welcomed.wait(), 30)
                await asyncio.wait_for(uplink.connected.wait(), 5)
            finally:
                run.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await run
    assert len(hellos) == 4
    assert not [r for r in caplog.records if r.levelname == "ERROR"], caplog.text
    assert sum("turned away" in r.getMessage() for r in caplog.records) == 3


class Blackhole:
    """A TCP hop in front of the stand-in platform (nginx in front of a machine): it
    forwards both ways until ``cut()``, after which what either side sends of the
    connections already open vanishes, and nothing is closed, as when the machine
    behind it drops off the network. Connections made after the cut are forwarded:
    the hop's other machines are still there."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = 0
        self._cut: list[asyncio.Event] = []
        self._tasks: set[asyncio.Task[None]] = set()

    def cut(self) -> None:
        for silenced in self._cut:
            silenced.set()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        silenced = asyncio.Event()
        self._cut.append(silenced)

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            while chunk := await src.read(65536):
                if not silenced.is_set():
                    dst.write(chunk)
            # An end of stream after the cut vanishes too: only the hop is still there.
            if not silenced.is_set():
                dst.close()
            else:
                await asyncio.Event().wait()

        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(pipe(reader, up_writer))
                group.create_task(pipe(up_reader, writer))
        except* (OSError, asyncio.CancelledError):
            pass
        finally:
            writer.transport.abort()
            up_writer.transport.abort()

    @contextlib.asynccontextmanager
    async def running(self) -> AsyncIterator[Blackhole]:
        server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = server.sockets[0].getsockname()[1]
        try:
            yield self
        finally:
            server.close()
            for task in list(self._tasks):
                task.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)


async def test_an_uplink_gone_silent_is_given_up_and_the_agent_connects_again(
    platform: Platform,
) -> None:
    interval, timeout = 0.2, 0.3
    async with Blackhole(platform.port).running() as hop:
        uplink = _uplink(
            hop.port,
            lambda msg: asyncio.sleep(0),
            reconnect_max_s=0.1,
            ping_interval_s=interval,
            ping_timeout_s=timeout,
        )
        run = asyncio.create_task(uplink.run())
        try:
            await asyncio.wait_for(uplink.connected.wait(), 5)
            first = await asyncio.wait_for(platform.connections.get(), 5)
            loop = asyncio.get_running_loop()
            hop.cut()
            cut_at = loop.time()
            # Heartbeats still go out (into the hop) and nothing comes back: only the
            # keepalive can tell. Bound: a ping, its timeout, the close; the backoff.
            second = await asyncio.wait_for(platform.connections.get(), 10)
            # Cleared when the first uplink was given up, set once registered again.
            await asyncio.wait_for(uplink.connected.wait(), 5)
            took = loop.time() - cut_at
            assert second is not first
            assert uplink.connections == 2
            assert took >= timeout, took
            # Generous beside the bound (a loaded machine), far below what websockets'
            # defaults (20 s, 20 s, 10 s) would take.
            assert took < interval + timeout + CLOSE_TIMEOUT_S + 3.0, took
        finally:
            run.cancel()
            with pytest.raises(asyncio.CancelledError):
                await run


def test_the_keepalive_is_the_agent_configs() -> None:
    config: dict[str, Any] = {
        "platform_url": "wss://iouv.example.org",
        "vehicle_id": "v-1",
        "credential": "c",
        "platform_public_key": PUBLIC_PEM,
        "adapter": "car",
    }
    default = AgentConfig.from_mapping(config)
    assert (default.uplink_ping_interval_s, default.uplink_ping_timeout_s) == (
        PING_INTERVAL_S,
        PING_TIMEOUT_S,
    )
    # The default bound on a silent uplink is the one docs/operations.md promises.
    assert PING_INTERVAL_S + PING_TIMEOUT_S + CLOSE_TIMEOUT_S <= 6.0
    set_ = AgentConfig.from_mapping(
        {**config, "uplink_ping_interval_s": 5, "uplink_ping_timeout_s": 7.5}
    )
    assert (set_.uplink_ping_interval_s, set_.uplink_ping_timeout_s) == (5.0, 7.5)
    for name in ("uplink_ping_interval_s", "uplink_ping_timeout_s"):
        for bad in (0, -1, "2", True, None):
            with pytest.raises(ConfigError, match=name):
                AgentConfig.from_mapping({**config, name: bad})


async def test_an_uplink_leaves_from_the_address_its_connect_options_name(
    platform: Platform,
) -> None:
    # A vehicle with two links binds its uplink to one (the scale benchmark gives each
    # light agent an address of its own, as a fleet has: nginx limits per address).
    uplink = _uplink(
        platform.port,
        lambda msg: asyncio.sleep(0),
        reconnect_max_s=0.1,
        connect_options={"local_addr": ("127.0.0.7", 0)},
    )
    run = asyncio.create_task(uplink.run())
    try:
        ws = await asyncio.wait_for(platform.connections.get(), 10)
        assert ws.remote_address[0] == "127.0.0.7"
        # Registered (its profile sent) before it is stopped, as the fixtures' uplinks
        # are: a cancel landing in websockets' send of the profile is not seen at once.
        await asyncio.wait_for(uplink.connected.wait(), 10)
    finally:
        run.cancel()
        with pytest.raises(asyncio.CancelledError):
            await run
