"""benchmarks.scale in quick mode, end to end, and the front proxy it runs the platform
behind.

The end-to-end test runs the real platform (two daphne processes on the test database,
the Redis channel layer), light agents in a worker process, two simulated cars and the
API clients, then checks that every output exists and is well formed. It asserts
nothing about timing: the machine may be busy.
"""

from __future__ import annotations

import asyncio
import csv
import json
import math
import socket
import struct
from pathlib import Path

import pytest
from django.conf import settings

from benchmarks import scale
from benchmarks.front_proxy import Backend, FrontProxy, Routes, Rule, request_path

# --------------------------------------------------------------------------------------
# The front proxy
# --------------------------------------------------------------------------------------


def test_routes_pick_the_longest_matching_prefix_else_the_default() -> None:
    agents, relay = Backend("127.0.0.1", 8001), Backend("127.0.0.1", 8003)
    users = Backend("127.0.0.1", 8002)
    routes = Routes(default=users, rules=[Rule("/ws/", relay), Rule("/ws/agent/", agents)])
    assert routes.backend_for("/ws/agent/") == agents
    assert routes.backend_for("/ws/agent/?v=1") == agents
    assert routes.backend_for("/ws/relay/abc/") == relay
    assert routes.backend_for("/api/v1/sessions") == users
    assert routes.backend_for("/") == users
    assert Routes(default=users).backend_for("/ws/agent/") == users


def test_request_lines_and_cli_texts_are_parsed_strictly() -> None:
    assert request_path(b"GET /ws/agent/ HTTP/1.1\r\n") == "/ws/agent/"
    assert request_path(b"POST /api/v1/sessions?x=1 HTTP/1.0\r\n") == "/api/v1/sessions?x=1"
    assert request_path(b"\x16\x03\x01 garbage\r\n") is None
    assert request_path(b"GET /\r\n") is None
    assert Rule.parse("/ws/agent/=127.0.0.1:8001") == Rule("/ws/agent/", Backend("127.0.0.1", 8001))
    assert Backend.parse("[::1]:8000") == Backend("::1", 8000)
    assert Backend.parse("127.0.0.1:0", any_port=True).port == 0
    for bad in ("127.0.0.1", "127.0.0.1:0", "127.0.0.1:http", ":80"):
        with pytest.raises(ValueError):
            Backend.parse(bad)
    for bad in ("ws/agent/=127.0.0.1:1", "/ws/agent/"):
        with pytest.raises(ValueError):
            Rule.parse(bad)


async def _backend(name: bytes) -> tuple[asyncio.Server, int, list[bytes]]:
    """A server that answers each connection with ``name`` and then echoes it back;
    the first bytes of each connection it got are kept in the list."""
    seen: list[bytes] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        first = await reader.readuntil(b"\r\n\r\n")
        seen.append(first)
        writer.write(name + b"|")
        while data := await reader.read(1024):
            writer.write(data)
            await writer.drain()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1], seen


async def _exchange(port: int, request: bytes, then: bytes) -> bytes:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request + then)
    await writer.drain()
    writer.write_eof()
    answer = await asyncio.wait_for(reader.read(), 5)
    writer.close()
    return answer


async def test_connections_are_routed_by_their_first_path_and_piped_both_ways() -> None:
    agents_server, agents_port, agents_seen = await _backend(b"agents")
    users_server, users_port, users_seen = await _backend(b"users")
    routes = Routes(
        default=Backend("127.0.0.1", users_port),
        rules=[Rule("/ws/agent/", Backend("127.0.0.1", agents_port))],
    )
    async with agents_server, users_server, FrontProxy(routes) as proxy:
        upgrade = b"GET /ws/agent/ HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n\r\n"
        assert await _exchange(proxy.port, upgrade, b"frames") == b"agents|frames"
        api = b"POST /api/v1/sessions HTTP/1.1\r\nHost: x\r\n\r\n"
        assert await _exchange(proxy.port, api, b"{}") == b"users|{}"
        # Bytes reach the backend untouched, the request line included.
        assert agents_seen == [upgrade]
        assert users_seen == [api]
        assert routes.counts == {f"127.0.0.1:{agents_port}": 1, f"127.0.0.1:{users_port}": 1}


async def test_garbage_gets_400_and_an_unreachable_backend_502() -> None:
    dead = scale.free_port()
    async with FrontProxy(Routes(default=Backend("127.0.0.1", dead))) as proxy:
        assert (await _exchange(proxy.port, b"\x16\x03\x01 hello\r\n", b"")).startswith(
            b"HTTP/1.1 400"
        )
        assert (await _exchange(proxy.port, b"GET / HTTP/1.1\r\n\r\n", b"")).startswith(
            b"HTTP/1.1 502"
        )


async def test_a_client_reset_is_passed_on_as_a_reset() -> None:
    """A browser that dies must look dead to the platform too, not like a clean close."""
    ended = asyncio.get_running_loop().create_future()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readuntil(b"\r\n\r\n")
        writer.write(b"ok")
        try:
            while await reader.read(1024):
                pass
            ended.set_result("eof")
        except ConnectionResetError:
            ended.set_result("reset")
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server, FrontProxy(Routes(default=Backend("127.0.0.1", port))) as proxy:
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(b"GET /ws/relay/x/ HTTP/1.1\r\n\r\n")
        assert await asyncio.wait_for(reader.readexactly(2), 5) == b"ok"
        # A zero linger time makes the kernel reset the connection instead of a FIN.
        sock = writer.get_extra_info("socket")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        writer.transport.abort()
        assert await asyncio.wait_for(ended, 5) == "reset"


# --------------------------------------------------------------------------------------
# Quick mode, end to end
# --------------------------------------------------------------------------------------


def _database_url() -> str:
    """The test database, for the daphne processes the benchmark starts."""
    db = settings.DATABASES["default"]
    password = f":{db['PASSWORD']}" if db.get("PASSWORD") else ""
    return (
        f"postgres://{db.get('USER') or ''}{password}@{db.get('HOST') or '127.0.0.1'}:"
        f"{db.get('PORT') or 5432}/{db['NAME']}"
    )


def _rows(path: Path, header: list[str]) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == header, path.name
        return list(reader)


def _number(text: str) -> float:
    value = float(text)
    assert math.isfinite(value) and value >= 0, text
    return value


@pytest.mark.postgres
@pytest.mark.redis
@pytest.mark.django_db(transaction=True)
def test_quick_mode_writes_every_output(tmp_path: Path) -> None:
    params = scale.Params.quick_mode(agents=20)
    scale.run(params, out=tmp_path, command="pytest quick mode", database_url=_database_url())

    usage = _rows(
        tmp_path / "resources.csv",
        ["topology", "phase", "process", "window_s", "cpu_pct_of_one_core", "rss_mb", "threads"],
    )
    processes = {(r["topology"], r["process"]) for r in usage}
    assert processes >= {
        ("one", "platform-1"),
        ("two", "platform-1 (agents)"),
        ("two", "platform-2 (users)"),
        ("one", "agent workers"),
        ("one", "API clients"),
    }
    for r in usage:
        _number(r["cpu_pct_of_one_core"])
        _number(r["rss_mb"])

    api = _rows(
        tmp_path / "api_requests.csv",
        ["topology", "client", "endpoint", "start_s", "latency_ms", "status", "session_id"],
    )
    for topology in ("one", "two"):
        mine = [r for r in api if r["topology"] == topology]
        assert any(r["endpoint"] == "request" and r["status"] == "201" for r in mine), topology
        for r in mine:
            _number(r["latency_ms"])

    deliveries = _rows(
        tmp_path / "task_delivery.csv", ["topology", "session_id", "request_to_agent_ms"]
    )
    assert any(d["request_to_agent_ms"] for d in deliveries)

    relay = _rows(tmp_path / "relay_rtt.csv", ["topology", "n", "rtt_ms"])
    assert {r["topology"] for r in relay} == {"one", "two"}

    trials = _rows(
        tmp_path / "reaction_trials.csv",
        ["topology", "mode", "trial", "reaction_ms", "agent_side_ms", "platform_logged"],
    )
    cases: dict[tuple[str, str], int] = {}
    for t in trials:
        _number(t["reaction_ms"])
        _number(t["agent_side_ms"])
        cases[(t["topology"], t["mode"])] = cases.get((t["topology"], t["mode"]), 0) + 1
    expected = {("one", mode) for mode in scale.MODES} | {
        ("two", mode) for mode in scale.MODES if mode.startswith("relay")
    }
    assert cases == {case: params.trials for case in expected}

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["params"]["agents"] == 20
    assert summary["machine"]["cores"] >= 1
    figures = summary["figures"]
    assert figures["agents"]["n"] == 20
    assert set(figures["api"]) == {"one", "two"}
    for topology in ("one", "two"):
        sessions = figures["api"][topology]["sessions"]
        assert sessions["task_deployed"] == sessions["sessions"] > 0
        assert sessions["task_accepted"] >= 1

    report = (tmp_path / "report.md").read_text()
    for heading in (
        "## Summary",
        "## Machine and run",
        "## 1. 20 agents on uplinks",
        "## 2. Assignment and task deployment",
        "## 3. Link loss to safe action",
        "## 4. One platform process against two",
    ):
        assert heading in report
    assert "Quick mode" in report
    assert "nan" not in report
