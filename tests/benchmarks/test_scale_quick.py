"""benchmarks.scale in quick mode, end to end (under production's server, uvicorn, and
under daphne for the heartbeat phase), the nginx front proxy it runs the platform behind
(benchmarks.nginx_proxy), and what its comparisons rest on (benchmarks.scale_compare,
another tree's code kept apart from this checkout's).

The proxy tests start a real nginx (Debian's, installed if missing; skipped with the
reason when it cannot be) in front of real backends on loopback. The end-to-end test
runs the real platform (two processes on the test database, the Redis channel
layer), light agents in a worker process, two simulated cars and the API clients, then
checks that every output exists and is well formed. It asserts nothing about timing:
the machine may be busy.
"""

from __future__ import annotations

import asyncio
import csv
import http.client
import http.server
import io
import json
import math
import os
import ssl
import subprocess
import sys
import threading
import time
import uuid
from collections import Counter
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from django.conf import settings
from websockets.asyncio.client import connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from benchmarks import scale
from benchmarks.nginx_proxy import (
    CLIENT_MAX_BODY_BYTES,
    AccessEntry,
    Backend,
    NginxProxy,
    NginxUnavailable,
    Routes,
    Rule,
    Tls,
    config_check,
    nginx_binary,
)
from benchmarks.scale_compare import compare_md
from benchmarks.scale_platform import SITECUSTOMIZE, PlatformTree
from services.web.api_schemas import MAX_BODY_BYTES
from tests.agents.waiting import until
from tests.tls import certificates_make


@pytest.fixture(scope="module")
def nginx() -> Path:
    try:
        return nginx_binary()
    except NginxUnavailable as exc:
        pytest.skip(f"needs nginx: {exc}")


# --------------------------------------------------------------------------------------
# The front proxy
# --------------------------------------------------------------------------------------


def _seen(name: str, path: str, headers: Headers) -> dict[str, Any]:
    """What a backend reports about a request it got."""
    return {
        "backend": name,
        "path": path,
        "host": headers.get("Host"),
        "forwarded_for": headers.get("X-Forwarded-For"),
        "forwarded_proto": headers.get("X-Forwarded-Proto"),
    }


class EchoBackend:
    """A WebSocket server that answers a plain GET with what it saw (JSON) and, on a
    WebSocket, first sends what it saw, then echoes each message prefixed with its
    name; :attr:`close_codes` holds how each WebSocket ended, as the server saw it."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.close_codes: asyncio.Queue[int] = asyncio.Queue()
        self.server: Server | None = None

    @property
    def backend(self) -> Backend:
        assert self.server is not None
        return Backend("127.0.0.1", self.server.sockets[0].getsockname()[1])

    def _plain(self, connection: ServerConnection, request: Request) -> Response | None:
        if request.headers.get("Upgrade"):
            return None  # the WebSocket handshake goes on
        return connection.respond(200, json.dumps(_seen(self.name, request.path, request.headers)))

    async def _handle(self, ws: ServerConnection) -> None:
        assert ws.request is not None
        await ws.send(json.dumps(_seen(self.name, ws.request.path, ws.request.headers)))
        try:
            async for message in ws:
                assert isinstance(message, str)
                await ws.send(f"{self.name}:{message}")
        except ConnectionClosed:
            pass
        # 1006 (abnormal closure) when the connection ended without a close frame.
        await self.close_codes.put(ws.close_code or 0)

    async def __aenter__(self) -> EchoBackend:
        self.server = await serve(self._handle, "127.0.0.1", 0, process_request=self._plain)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()
        await self.server.wait_closed()


def _request(port: int, method: str, path: str, body: bytes | None = None) -> tuple[int, bytes]:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.request(method, path, body=body)
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


async def _get(port: int, path: str) -> tuple[int, bytes]:
    return await asyncio.to_thread(_request, port, "GET", path)


@pytest.fixture
async def backends(nginx: Path) -> AsyncIterator[dict[str, EchoBackend]]:
    async with (
        EchoBackend("agents") as agents,
        EchoBackend("relay") as relay,
        EchoBackend("users") as users,
    ):
        yield {"agents": agents, "relay": relay, "users": users}


async def test_nginx_routes_by_the_longest_prefix_and_carries_websockets(
    backends: dict[str, EchoBackend],
) -> None:
    by_address = {b.backend: name for name, b in backends.items()}
    routes = Routes(
        default=backends["users"].backend,
        rules=[
            Rule("/ws/", backends["relay"].backend),
            Rule("/ws/agent/", backends["agents"].backend),
        ],
    )
    async with NginxProxy(routes) as proxy:
        front = f"127.0.0.1:{proxy.port}"
        sockets = {
            "/ws/agent/": "agents",
            "/ws/agent/?v=1": "agents",
            "/ws/relay/abc/": "relay",
            "/ws/agents/": "relay",  # not under /ws/agent/, but under /ws/
        }
        for path, expected in sockets.items():
            assert by_address[routes.backend_for(path)] == expected
            async with connect(f"ws://{front}{path}", proxy=None) as ws:
                seen = json.loads(await ws.recv())
                assert seen == {
                    "backend": expected,
                    "path": path,
                    "host": front,  # daphne builds URLs from it
                    "forwarded_for": "127.0.0.1",
                    "forwarded_proto": "http",
                }
                await ws.send("ping")
                assert await ws.recv() == f"{expected}:ping"
            # A polite close reaches the backend as one.
            assert await asyncio.wait_for(backends[expected].close_codes.get(), 10) == 1000

        for path in ("/api/v1/sessions?x=1", "/"):
            status, body = await _get(proxy.port, path)
            assert status == 200
            assert json.loads(body)["backend"] == "users"
            assert json.loads(body)["path"] == path
        # nginx's own rule for a prefix ending in "/": the bare name is redirected to it.
        assert (await _get(proxy.port, "/ws/agent"))[0] == 301

        # nginx logs a WebSocket once it has ended, and a request just after answering
        # it: the last line may come a moment after the answer.
        await until(lambda: len(proxy.requests()) >= len(sockets) + 3, within=5, what="the log")
        assert proxy.requests() == [
            *(AccessEntry("GET", path, 101, str(routes.backend_for(path))) for path in sockets),
            AccessEntry("GET", "/api/v1/sessions?x=1", 200, str(backends["users"].backend)),
            AccessEntry("GET", "/", 200, str(backends["users"].backend)),
            AccessEntry("GET", "/ws/agent", 301, "-"),
        ]


async def test_a_client_that_vanishes_looks_dead_to_the_backend(
    backends: dict[str, EchoBackend],
) -> None:
    """A browser whose socket dies without a close frame must look dead to the
    platform too (code 1006, no close frame), not like a user who left."""
    relay = backends["relay"]
    async with NginxProxy(Routes(default=relay.backend)) as proxy:
        ws = await connect(f"ws://127.0.0.1:{proxy.port}/ws/relay/x/", proxy=None)
        await ws.recv()
        ws.transport.abort()
        assert await asyncio.wait_for(relay.close_codes.get(), 10) == 1006


def _request_tls(
    port: int, path: str, context: ssl.SSLContext, host: str = "localhost"
) -> tuple[int, bytes]:
    connection = http.client.HTTPSConnection(host, port, timeout=10, context=context)
    try:
        connection.request("GET", path)
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


async def test_with_tls_nginx_serves_https_and_wss_and_redirects_plain_http(
    backends: dict[str, EchoBackend], tmp_path: Path
) -> None:
    """TLS ends at nginx, as in production: the backends hear plain http with
    ``X-Forwarded-Proto: https`` and the client's Host; port "80" redirects."""
    certs = certificates_make(tmp_path / "certs")
    routes = Routes(
        default=backends["users"].backend, rules=[Rule("/ws/", backends["relay"].backend)]
    )
    tls = Tls(certs.chain, certs.key)
    async with NginxProxy(routes, tls=tls, redirect_port=0) as proxy:
        front = f"localhost:{proxy.port}"
        assert proxy.url == f"https://127.0.0.1:{proxy.port}"
        context = certs.client_context()  # checks the chain and the name
        status, body = await asyncio.to_thread(_request_tls, proxy.port, "/api/v1/x", context)
        assert status == 200
        assert json.loads(body) == {
            "backend": "users",
            "path": "/api/v1/x",
            "host": front,
            "forwarded_for": "127.0.0.1",
            "forwarded_proto": "https",
        }
        async with connect(f"wss://{front}/ws/relay/s/", proxy=None, ssl=context) as ws:
            seen = json.loads(await ws.recv())
            assert (seen["backend"], seen["forwarded_proto"], seen["host"]) == (
                "relay",
                "https",
                front,
            )
            await ws.send("ping")
            assert await ws.recv() == "relay:ping"
        # A client that does not trust the CA is refused by its own TLS stack.
        with pytest.raises(ssl.SSLCertVerificationError):
            await asyncio.to_thread(_request_tls, proxy.port, "/", ssl.create_default_context())

        # Plain http on the redirect port: a 301 to the same path on https, with its port.
        assert proxy.redirect_url is not None and proxy.redirect_port is not None
        connection = http.client.HTTPConnection("localhost", proxy.redirect_port, timeout=10)
        try:
            await asyncio.to_thread(connection.request, "GET", "/accounts/login/?next=/x")
            response = await asyncio.to_thread(connection.getresponse)
            assert response.status == 301
            assert response.getheader("Location") == (
                f"https://localhost:{proxy.port}/accounts/login/?next=/x"
            )
        finally:
            connection.close()
        # Plain http on the TLS port gets nginx's 400, never the backend.
        assert (await _get(proxy.port, "/"))[0] == 400
        assert all(
            entry.upstream == "-" for entry in proxy.requests() if entry.status in (301, 400)
        )


async def _http_server(handle: Any) -> tuple[asyncio.Server, Backend]:
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    return server, Backend("127.0.0.1", server.sockets[0].getsockname()[1])


async def test_bodies_the_platform_accepts_or_answers_itself_pass_larger_ones_get_413(
    nginx: Path,
) -> None:
    # nginx admits every body the platform accepts (the admin's forms: Django's limit)
    # and the API's oversized ones, which the platform refuses in its own words.
    assert CLIENT_MAX_BODY_BYTES >= settings.DATA_UPLOAD_MAX_MEMORY_SIZE > MAX_BODY_BYTES

    async def body_length(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = (await reader.readuntil(b"\r\n\r\n")).decode().lower()
        length = int(head.partition("content-length:")[2].split()[0])
        answer = str(len(await reader.readexactly(length))).encode()
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Length: %d\r\n\r\n%s" % (len(answer), answer))
        await writer.drain()
        writer.close()

    server, backend = await _http_server(body_length)
    async with server, NginxProxy(Routes(default=backend)) as proxy:
        for size in (MAX_BODY_BYTES + 1, CLIENT_MAX_BODY_BYTES):
            # Bodies this large go through nginx's temporary files, under its prefix.
            status, body = await asyncio.to_thread(
                _request, proxy.port, "POST", "/api/v1/sessions", b"x" * size
            )
            assert (status, body) == (200, str(size).encode())
        # One byte more is refused on the announced length alone, before any body.
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(
            b"POST /api/v1/sessions HTTP/1.1\r\nHost: x\r\nContent-Length: %d\r\n\r\n"
            % (CLIENT_MAX_BODY_BYTES + 1)
        )
        assert (await asyncio.wait_for(reader.readline(), 10)).startswith(b"HTTP/1.1 413")
        writer.close()


async def test_an_unreachable_backend_gets_502_and_nginx_leaves_nothing_behind(
    nginx: Path,
) -> None:
    proxy = NginxProxy(Routes(default=Backend("127.0.0.1", scale.free_port())))
    async with proxy:
        assert (await _get(proxy.port, "/api/v1/vehicles"))[0] == 502
        assert proxy.process is not None and proxy.process.returncode is None
    assert proxy.process.returncode is not None
    assert not proxy.prefix.exists()
    with pytest.raises(OSError):
        await asyncio.open_connection("127.0.0.1", proxy.port)


async def test_a_port_taken_by_another_program_fails_the_start_with_nginx_s_words(
    nginx: Path,
) -> None:
    """Something else accepting on the port is not taken for nginx being ready."""
    other, other_at = await _http_server(lambda reader, writer: writer.close())
    async with other:
        proxy = NginxProxy(Routes(default=other_at), port=other_at.port)
        with pytest.raises(RuntimeError, match="Address already in use"):
            async with proxy:
                pass
    assert proxy.process is not None and proxy.process.returncode is not None
    assert not proxy.prefix.exists()


def test_the_generated_configuration_passes_nginx_t(nginx: Path, tmp_path: Path) -> None:
    routes = Routes(
        default=Backend("127.0.0.1", 8002),
        rules=[Rule("/ws/agent/", Backend("127.0.0.1", 8001)), Rule("/ws/", Backend("::1", 8003))],
    )
    NginxProxy(routes, port=8000, prefix=tmp_path).write_config()
    assert "test is successful" in config_check(tmp_path, nginx)


def test_the_generated_tls_configuration_passes_nginx_t(nginx: Path, tmp_path: Path) -> None:
    certs = certificates_make(tmp_path / "certs")
    routes = Routes(default=Backend("127.0.0.1", 8002))
    tls = Tls(certs.chain, certs.key)
    NginxProxy(routes, port=8443, prefix=tmp_path, tls=tls, redirect_port=8080).write_config()
    config = (tmp_path / "nginx.conf").read_text()
    assert "listen 127.0.0.1:8443 ssl" in config
    assert "return 301 https://$host:8443$request_uri;" in config
    assert "test is successful" in config_check(tmp_path, nginx)
    with pytest.raises(ValueError, match="needs TLS"):
        NginxProxy(routes, redirect_port=8080)
    with pytest.raises(ValueError, match="TLS file path"):
        Tls(Path("/etc/ssl/a b.pem"), certs.key)


def test_addresses_and_rules_are_parsed_strictly() -> None:
    assert Rule.parse("/ws/agent/=127.0.0.1:8001") == Rule("/ws/agent/", Backend("127.0.0.1", 8001))
    assert Backend.parse("[::1]:8000") == Backend("::1", 8000)
    assert str(Backend("::1", 8000)) == "[::1]:8000"
    assert Backend.parse("127.0.0.1:0", any_port=True).port == 0
    for bad in ("127.0.0.1", "127.0.0.1:0", "127.0.0.1:http", ":80"):
        with pytest.raises(ValueError):
            Backend.parse(bad)
    # A prefix is written into nginx.conf: nothing that could end a directive.
    for bad in ("ws/agent/=127.0.0.1:1", "/ws/agent/", "/ws/;x=127.0.0.1:1", "/a b=127.0.0.1:1"):
        with pytest.raises(ValueError):
            Rule.parse(bad)
    users = Backend("127.0.0.1", 8002)
    for rules in ([Rule("/", users)], [Rule("/ws/", users), Rule("/ws/", users)]):
        with pytest.raises(ValueError):
            Routes(default=users, rules=rules)


# --------------------------------------------------------------------------------------
# Quick mode, end to end
# --------------------------------------------------------------------------------------


def _logs_tail() -> str:
    """The end of the run's front proxy and platform logs: why requests failed."""
    runs = Path(settings.VAR_DIR) / "bench-scale"
    tails = []
    for log in sorted(runs.glob("*/proxy-*.log")) + sorted(runs.glob("*/platform-*.log")):
        tails.append(f"--- {log.name}\n{log.read_text(errors='replace')[-1500:]}")
    return "\n".join(tails)


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
@pytest.mark.cost(30)  # the benchmark's quick run, end to end
def test_quick_mode_writes_every_output(nginx: Path, tmp_path: Path) -> None:
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
        statuses = Counter((r["endpoint"], r["status"]) for r in mine)
        assert statuses[("request", "201")], (topology, statuses, _logs_tail())
        for r in mine:
            _number(r["latency_ms"])

    deliveries = _rows(
        tmp_path / "task_delivery.csv", ["topology", "session_id", "request_to_agent_ms"]
    )
    assert any(d["request_to_agent_ms"] for d in deliveries)

    relay = _rows(tmp_path / "relay_rtt.csv", ["topology", "n", "rtt_ms"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    for topology in ("one", "two"):
        # Round trips measured, or the run says why none were: on a saturated machine
        # every command of a short window may outlast LOST_AFTER_S (counted lost), or the
        # relayed session may fail to start (a note names the error).
        measured = any(r["topology"] == topology for r in relay)
        lost = summary["figures"]["relay"][topology]["lost"] > 0
        failed = any(
            n.startswith(f"{topology}: the relayed control session failed")
            for n in summary["notes"]
        )
        assert measured or lost or failed, (topology, summary["notes"], _logs_tail())

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
    summary = json.loads((tmp_path / "summary.json").read_text())
    # The run's notes say why a trial was missing (a retry, a spent budget).
    assert cases == {case: params.trials for case in expected}, summary["notes"]

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
        "## CPU per role",
        "## 5. Login flood",
        "## 6. The fleet at 30 agents",
    ):
        assert heading in report
    assert "Quick mode" in report
    assert "nan" not in report
    _flood_checked(tmp_path, summary, params)


def _flood_checked(out: Path, summary: dict[str, Any], params: scale.Params) -> None:
    """The login flood's outputs: the flood's attempts each answered (or counted as a
    failed connection), the API clients' requests in both windows, its figures."""
    attempts = _rows(
        out / "login_flood.csv",
        ["window", "client", "start_s", "latency_ms", "status", "answered_by"],
    )
    assert attempts, "no login attempt was made"
    assert {int(a["client"]) for a in attempts} <= set(range(params.flood_clients))
    for a in attempts:
        _number(a["latency_ms"])
        # A wrong password: the form again (200), or refused (429 from nginx or the
        # lockout); never let in (302) nor a CSRF failure (403).
        assert a["status"] in ("200", "429"), a
    api = _rows(
        out / "flood_api_requests.csv",
        ["window", "client", "endpoint", "start_s", "latency_ms", "status", "session_id"],
    )
    # The API clients read the catalogue and request sessions; which window each answer
    # falls in is timing (a quick window is 2 s, and a client process started late on
    # a busy machine may see little of one): what each window had is the report's.
    assert {r["window"] for r in api} <= set(scale.FLOOD_WINDOWS)
    assert any(r["endpoint"] == "services" and r["status"] == "200" for r in api), api[:5]
    assert any(r["endpoint"] == "request" and r["status"] == "201" for r in api), api[:5]
    flood = summary["figures"]["flood"]
    assert flood["attempts"] == len(attempts)
    assert sum(flood["answers"].values()) == len(attempts)
    for window in scale.FLOOD_WINDOWS:
        mine = [r for r in api if r["window"] == window and r["endpoint"] == "services"]
        assert flood["api"][window]["services_ms"]["n"] == sum(
            r["status"] == "200" for r in mine
        ), window
    fleet = summary["figures"]["fleet_phase"]
    assert fleet["agents"] == params.fleet_agents
    assert fleet["heartbeats_per_s"] > 0


@pytest.mark.postgres
@pytest.mark.redis
@pytest.mark.django_db(transaction=True)
@pytest.mark.cost(30)  # the benchmark's quick run in the production shape
def test_quick_mode_runs_the_production_shape_from_deploy_s_files(
    nginx: Path, tmp_path: Path
) -> None:
    params = replace(scale.Params.quick_mode(agents=10), topology="production", phases="one")
    scale.run(params, out=tmp_path, command="pytest production", database_url=_database_url())

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["machine"]["topology"].startswith("production: 1 gunicorn")
    usage = _rows(
        tmp_path / "resources.csv",
        ["topology", "phase", "process", "window_s", "cpu_pct_of_one_core", "rss_mb", "threads"],
    )
    # CPU summed per role: the gunicorn and uvicorn processes, nginx, Celery.
    expected = {
        "platform: gunicorn",
        "platform: uvicorn",
        "nginx (front proxy)",
        "celery (worker + beat)",
    }
    assert {r["process"] for r in usage if r["phase"] == "API load"} >= expected
    assert set(summary["figures"]["roles"]["login flood: during"]) >= expected
    figures = summary["figures"]
    assert figures["agents"]["online_min"] == 10
    sessions = figures["api"]["one"]["sessions"]
    assert sessions["task_deployed"] == sessions["sessions"] > 0
    # The relay crossed processes: the car's uplink and the controller may be on
    # different uvicorn processes, the API on gunicorn's.
    assert figures["relay"]["one"]["n"] > 0
    # Every process of the shape logged its work and no traceback.
    logs = summary["platform_logs"]
    assert {"gunicorn-1", "uvicorn-1", "uvicorn-2", "iouv-worker", "iouv-beat"} <= set(logs)
    assert all(counts["tracebacks"] == 0 for counts in logs.values()), logs
    _flood_checked(tmp_path, summary, params)
    report = (tmp_path / "report.md").read_text()
    assert "served by production" in report
    assert "## 4." not in report  # one process against two: the single topology's
    assert "nan" not in report


@pytest.mark.postgres
@pytest.mark.redis
@pytest.mark.django_db(transaction=True)
def test_daphne_serves_the_agents_and_the_report_says_so(nginx: Path, tmp_path: Path) -> None:
    # The other server the platform runs under (the quick runs above are production's).
    params = replace(scale.Params.quick_mode(agents=10), server="daphne", phases="heartbeats")
    scale.run(params, out=tmp_path, command="pytest daphne", database_url=_database_url())

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["machine"]["server"] == "daphne"
    agents = summary["figures"]["agents"]
    assert agents["online_min"] == 10
    assert agents["heartbeats_per_s"] > 0
    assert _number(agents["cpu_ms_per_heartbeat"]) > 0
    assert summary["platform_logs"]["platform-1"]["tracebacks"] == 0
    report = (tmp_path / "report.md").read_text()
    assert "served by single: one daphne process serving everything" in report
    assert "## 1. 10 agents on uplinks" in report
    assert "## 2." not in report  # the heartbeat phase only
    assert "nan" not in report


# --------------------------------------------------------------------------------------
# Comparisons: runs side by side, another tree's code
# --------------------------------------------------------------------------------------


def test_variants_run_the_baseline_first_and_are_labelled_by_what_differs() -> None:
    current = PlatformTree()
    old = PlatformTree(Path("/tmp/x"), "abc123", "abc123" * 6)
    assert [(v.label, v.folder) for v in scale.variants([current], ["daphne"])] == [("daphne", "")]
    assert [v.label for v in scale.variants([old, current], ["daphne"])] == ["before", "after"]
    assert [v.folder for v in scale.variants([old, current], ["daphne", "uvicorn"])] == [
        "before-daphne",
        "before-uvicorn",
        "after-daphne",
        "after-uvicorn",
    ]
    # The paired run: one tree, each topology; the production shape serves with uvicorn.
    paired = scale.variants([current], ["uvicorn"], ["single", "production"])
    assert [(v.label, v.folder, v.topology) for v in paired] == [
        ("single", "single", "single"),
        ("production", "production", "production"),
    ]
    assert [v.label for v in scale.variants([current], ["daphne"], ["single", "production"])] == [
        "single"
    ]


def _summary(server: str, ms_per_heartbeat: float | None, api: bool) -> dict[str, Any]:
    figures: dict[str, Any] = {
        "agents": {"n": 100, "cpu_pct": 20.0, "cpu_ms_per_heartbeat": ms_per_heartbeat},
        "stages": [{"agents": 100, "cpu_pct": 20.0, "cpu_ms_per_heartbeat": ms_per_heartbeat}],
        "api": {},
        "relay": {},
        "reaction": {},
    }
    if api:
        figures["api"]["one"] = {
            "sessions_per_s": 31.5,
            "request_ms": {"n": 1, "p50": 40.0, "p95": 90.0},
        }
        figures["relay"]["one"] = {"n": 3, "p50": 5.0, "p95": 12.0, "lost": 0}
    return {"machine": {"server": server}, "params": {"agents": 100}, "figures": figures}


def test_the_comparison_puts_each_figure_side_by_side_with_its_target() -> None:
    report = compare_md(
        [
            ("daphne", "daphne", _summary("daphne", 0.2, api=True)),
            ("uvicorn", "uvicorn", _summary("uvicorn", None, api=False)),
        ],
        command="python -m benchmarks.scale --servers daphne,uvicorn",
    )
    assert "| | [daphne](daphne/report.md) | [uvicorn](uvicorn/report.md) | target |" in report
    assert "| ASGI server | daphne | uvicorn |  |" in report
    assert "| **platform CPU per heartbeat (ms)** | 0.200 | n/a | ≤ 0.15 |" in report
    assert "| 100 agents: CPU % / ms per heartbeat | 20 / 0.200 | 20 / n/a |  |" in report
    # A figure one run lacks (it ran the heartbeat phase only) is n/a, not an error.
    assert "| API load: sessions per s | 31.5 | n/a | ≥ 30 |" in report
    assert "| API load: relayed round trip p50 / p95 (ms) | 5.0 / 12.0 | n/a | p95 ≤ 20 |" in report


def test_another_tree_runs_its_own_modules_only(tmp_path: Path) -> None:
    """A module of this checkout's packages that the older tree lacks is not found in
    this checkout instead (the virtualenv's editable install would find it there)."""
    tree = tmp_path / "tree"
    (tree / "fleet").mkdir(parents=True)
    (tree / "fleet" / "__init__.py").write_text("")
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    probe = "import fleet; print(fleet.__file__); import fleet.liveness"
    env = PlatformTree(tree, "old", "0" * 40, extra_path=(site,)).env(dict(os.environ))
    done = subprocess.run(
        [sys.executable, "-P", "-c", probe], env=env, cwd=tree, capture_output=True, text=True
    )
    assert done.stdout.strip() == str(tree / "fleet" / "__init__.py")
    assert "No module named 'fleet.liveness'" in done.stderr


class _SessionsApi(http.server.BaseHTTPRequestHandler):
    """What the API clients need of the platform: a session on request, 200 on end."""

    protocol_version = "HTTP/1.1"

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers.get("Content-Length", 0)))
        body: dict[str, Any]
        if self.path == "/api/v1/sessions":
            status, body = 201, {"session": {"id": str(uuid.uuid4())}}
        else:
            status, body = 200, {"state": "ended"}
        raw = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(raw)))
        self.end_headers()
        self.wfile.write(raw)

    def log_message(self, *args: object) -> None:
        pass


def test_paced_clients_start_sessions_at_the_rate_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _SessionsApi)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        out = tmp_path / "api.csv"
        start = time.time() + 0.5
        spec = {
            "base": f"http://127.0.0.1:{server.server_address[1]}",
            "tokens": ["a", "b", "c"],
            "service": "light",
            "duration_s": 2.0,
            "rate": 10.0,
            "out": str(out),
        }
        (tmp_path / "spec.json").write_text(json.dumps(spec))
        # The start as the benchmark sends it, once the worker said it was ready.
        monkeypatch.setattr("sys.stdin", io.StringIO(json.dumps({"start_wall": start}) + "\n"))
        scale.api_worker(str(tmp_path / "spec.json"))
        assert capsys.readouterr().out.splitlines()[0] == '{"ready": true}'

    finally:
        server.shutdown()
        server.server_close()
    with out.open() as f:
        rows = list(csv.DictReader(f))
    requests = sorted(float(r["start_wall"]) - start for r in rows if r["endpoint"] == "request")
    # 10 a second for 2 s, shared by the three clients: 20 sessions, each at its turn
    # (a client never starts one early; it may start late on a busy machine).
    assert len(requests) == 20, requests
    assert all(at >= i / 10.0 - 0.005 for i, at in enumerate(requests)), requests
    assert sum(r["endpoint"] == "end" and r["status"] == "200" for r in rows) == 20
