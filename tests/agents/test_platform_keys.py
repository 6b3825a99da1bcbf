"""Where an agent's platform keys come from: its config (PEM, JWKS file, JWKS URL) and the
platform's ``welcome`` (how a key rotation reaches an enrolled agent)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
import time
from collections.abc import AsyncIterator, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat
from websockets.asyncio.server import ServerConnection, serve

from agents.config import JWKS_MAX_BYTES, AgentConfig, ConfigError, jwks_fetch
from agents.protocol import (
    PROTOCOL_VERSION,
    KeySet,
    Limits,
    VehicleTask,
    generate_keypair,
    jwks_from_keys,
    key_thumbprint,
    load_private_key,
    load_public_key,
)
from agents.runtime import _server_authenticated
from agents.simulation import agent_simulated_run

OLD_PRIVATE_PEM, OLD_PUBLIC_PEM = generate_keypair()
NEW_PRIVATE_PEM, NEW_PUBLIC_PEM = generate_keypair()
OLD_PUBLIC = load_public_key(OLD_PUBLIC_PEM)
NEW_PUBLIC = load_public_key(NEW_PUBLIC_PEM)
JWKS = jwks_from_keys([NEW_PUBLIC, OLD_PUBLIC])
VEHICLE = "car-keys"


def config_data(**extra: Any) -> dict[str, Any]:
    return {
        "platform_url": "wss://iouv.example.org",
        "vehicle_id": VEHICLE,
        "credential": "secret",
        "adapter": "car",
        **extra,
    }


# ---------------------------------------------------------------------------------------
# Config: PEM and JWKS file
# ---------------------------------------------------------------------------------------


def test_pem_config_still_works() -> None:
    config = AgentConfig.from_mapping(config_data(platform_public_key=OLD_PUBLIC_PEM))
    assert config.platform_keys().kids == [key_thumbprint(OLD_PUBLIC)]


def test_jwks_file_alone_gives_every_key(tmp_path: Path) -> None:
    (tmp_path / "jwks.json").write_text(json.dumps(JWKS))
    config = AgentConfig.from_mapping(
        config_data(platform_jwks_file="jwks.json"), base_dir=tmp_path
    )
    assert config.platform_keys() == KeySet.from_keys([NEW_PUBLIC, OLD_PUBLIC])


def test_pem_and_jwks_are_both_trusted(tmp_path: Path) -> None:
    (tmp_path / "jwks.json").write_text(json.dumps(jwks_from_keys([NEW_PUBLIC])))
    config = AgentConfig.from_mapping(
        config_data(platform_public_key=OLD_PUBLIC_PEM, platform_jwks_file="jwks.json"),
        base_dir=tmp_path,
    )
    assert set(config.platform_keys().kids) == {
        key_thumbprint(OLD_PUBLIC),
        key_thumbprint(NEW_PUBLIC),
    }


@pytest.mark.parametrize(
    "content, words",
    [
        ("not json", "not JSON"),
        (json.dumps({"keys": []}), "1 to"),
        (json.dumps({"keys": [{"kty": "RSA", "n": "AQAB", "e": "AQAB"}]}), "Ed25519"),
    ],
)
def test_bad_jwks_file_refused_naming_it(tmp_path: Path, content: str, words: str) -> None:
    (tmp_path / "jwks.json").write_text(content)
    with pytest.raises(ConfigError, match=f"platform_jwks_file: .*{words}"):
        AgentConfig.from_mapping(config_data(platform_jwks_file="jwks.json"), base_dir=tmp_path)


def test_unusable_pem_refused_naming_it() -> None:
    p256 = ec.generate_private_key(ec.SECP256R1()).public_key()
    pem = p256.public_bytes(Encoding.PEM, PublicFormat.SubjectPublicKeyInfo).decode()
    with pytest.raises(ConfigError, match=r"platform_public_key: .*Ed25519"):
        AgentConfig.from_mapping(config_data(platform_public_key=pem))
    with pytest.raises(ConfigError, match="platform_public_key: "):
        AgentConfig.from_mapping(
            config_data(
                platform_public_key="-----BEGIN PUBLIC KEY-----\nx\n-----END PUBLIC KEY-----"
            )
        )


def test_no_key_at_all_refused() -> None:
    with pytest.raises(ConfigError, match="platform_public_key"):
        AgentConfig.from_mapping(config_data())


def test_missing_jwks_file_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="platform_jwks_file: cannot read"):
        AgentConfig.from_mapping(config_data(platform_jwks_file="nope.json"), base_dir=tmp_path)


# ---------------------------------------------------------------------------------------
# Config: JWKS URL, against a real HTTP server
# ---------------------------------------------------------------------------------------


class _Handler(BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        if self.path == "/slow":
            time.sleep(1.5)
        if self.path == "/.well-known/jwks.json" or self.path == "/slow":
            body = json.dumps(JWKS).encode()
        elif self.path == "/huge":
            body = b" " * (JWKS_MAX_BYTES + 10)
        elif self.path == "/rsa":
            body = json.dumps({"keys": [{"kty": "RSA", "n": "AQAB", "e": "AQAB"}]}).encode()
        else:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        with contextlib.suppress(OSError):
            self.wfile.write(body)

    def log_message(self, *args: Any) -> None:
        pass


@pytest.fixture(scope="module")
def jwks_server() -> Iterator[str]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def test_jwks_url_is_fetched_at_load(jwks_server: str) -> None:
    config = AgentConfig.from_mapping(
        config_data(platform_jwks_url=f"{jwks_server}/.well-known/jwks.json")
    )
    assert config.platform_keys() == KeySet.from_keys([NEW_PUBLIC, OLD_PUBLIC])


@pytest.mark.parametrize(
    "path, words",
    [
        ("/missing", "answered 404"),
        ("/huge", f"over {JWKS_MAX_BYTES} bytes"),
        ("/rsa", "Ed25519"),
    ],
)
def test_jwks_url_failures_are_config_errors(jwks_server: str, path: str, words: str) -> None:
    with pytest.raises(ConfigError, match=f"platform_jwks_url: .*{words}"):
        AgentConfig.from_mapping(config_data(platform_jwks_url=jwks_server + path))


def test_jwks_url_times_out(jwks_server: str) -> None:
    with pytest.raises(ConfigError, match="platform_jwks_url: cannot fetch"):
        jwks_fetch(f"{jwks_server}/slow", timeout_s=0.3)


def test_unreachable_jwks_url_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="platform_jwks_url: cannot fetch"):
        jwks_fetch("http://127.0.0.1:9/.well-known/jwks.json", timeout_s=2)


@pytest.mark.parametrize(
    "url",
    ["http://iouv.example.org/.well-known/jwks.json", "ftp://127.0.0.1/jwks.json", "file:///etc"],
)
def test_jwks_url_must_be_authenticated(url: str) -> None:
    # Refused before any connection: plain http to another host could be anyone.
    with pytest.raises(ConfigError, match="https://"):
        jwks_fetch(url)


# ---------------------------------------------------------------------------------------
# Welcome: a rotation reaches a running agent
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "url, trusted",
    [
        ("wss://iouv.example.org/ws/agent/", True),
        ("ws://127.0.0.1:8000/ws/agent/", True),
        ("ws://[::1]:8000/ws/agent/", True),
        ("ws://localhost:8000/ws/agent/", True),
        ("ws://iouv.example.org/ws/agent/", False),
        ("ws://10.0.0.5:8000/ws/agent/", False),
    ],
)
def test_welcome_keys_trusted_only_from_an_authenticated_server(url: str, trusted: bool) -> None:
    assert _server_authenticated(url) is trusted


class RotatedPlatform:
    """A stand-in platform that already signs with the new key and says so in welcome."""

    def __init__(self, welcome_jwks: dict[str, Any] | None) -> None:
        self.welcome_jwks = welcome_jwks
        self.answers: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

    async def handle(self, ws: ServerConnection) -> None:
        hello = json.loads(await ws.recv())
        assert hello["type"] == "hello" and hello["v"] == PROTOCOL_VERSION
        welcome: dict[str, Any] = {
            "type": "welcome",
            "v": PROTOCOL_VERSION,
            "heartbeat_interval_s": 30,
        }
        if self.welcome_jwks is not None:
            welcome["platform_jwks"] = self.welcome_jwks
        await ws.send(json.dumps(welcome))
        now = time.time()
        task = VehicleTask(
            session_id="s-rotated",
            vehicle_id=VEHICLE,
            user="alice",
            allowed_commands=("stop",),
            limits=Limits(),
            issued_at=now,
            expires_at=now + 60,
        )
        await ws.send(
            json.dumps({"type": "task", "token": task.sign(load_private_key(NEW_PRIVATE_PEM))})
        )
        with contextlib.suppress(Exception):
            async for raw in ws:
                msg = json.loads(raw)
                if msg["type"] in ("task_accepted", "task_refused"):
                    await self.answers.put(msg)


@contextlib.asynccontextmanager
async def agent_against(platform: RotatedPlatform, **config: Any) -> AsyncIterator[RotatedPlatform]:
    async with serve(platform.handle, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        # Enrolled before the rotation: the agent's config knows only the old key.
        agent_config = AgentConfig.from_mapping(
            config_data(
                platform_url=f"ws://127.0.0.1:{port}",
                platform_public_key=OLD_PUBLIC_PEM,
                adapter_options={},
                **config,
            )
        )
        run = asyncio.create_task(agent_simulated_run(agent_config))
        try:
            yield platform
        finally:
            run.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await run


async def test_agent_adopts_the_welcome_jwks_and_accepts_a_task_signed_with_the_new_key() -> None:
    async with agent_against(RotatedPlatform(JWKS)) as platform:
        answer = await asyncio.wait_for(platform.answers.get(), 30)
    assert answer == {"type": "task_accepted", "session_id": "s-rotated"}


async def test_without_the_welcome_jwks_the_new_key_is_unknown() -> None:
    async with agent_against(RotatedPlatform(None)) as platform:
        answer = await asyncio.wait_for(platform.answers.get(), 30)
    assert answer["type"] == "task_refused" and answer["code"] == "unknown_key"
    assert answer["session_id"] == "s-rotated"  # the refusal names the task's session


async def test_pinned_agent_ignores_the_welcome_jwks() -> None:
    async with agent_against(RotatedPlatform(JWKS), platform_jwks_from_welcome=False) as platform:
        answer = await asyncio.wait_for(platform.answers.get(), 30)
    assert answer["type"] == "task_refused" and answer["code"] == "unknown_key"


async def test_an_unusable_welcome_jwks_keeps_the_configured_keys() -> None:
    bad = {"keys": [{"kty": "RSA", "n": "AQAB", "e": "AQAB"}]}
    async with agent_against(RotatedPlatform(bad)) as platform:
        answer = await asyncio.wait_for(platform.answers.get(), 30)
    assert answer["type"] == "task_refused" and answer["code"] == "unknown_key"
