"""A private Janus (the SFU) for a test: Debian's ``janus`` with a configuration of its
own in a temporary folder, on free ports, loading only the VideoRoom plugin and the HTTP
and WebSocket transports, with the token and admin secrets production uses
(``deploy/janus/``, docs/video.md "The SFU").

``janus`` and ``janus-tools`` (janus-pp-rec) are installed when missing, as the network
lab installs coturn (tests.netlab.ensure_packages: needs root).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import secrets
import shutil
import signal
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aiortc import MediaStreamTrack, RTCConfiguration, RTCPeerConnection, RTCSessionDescription

from agents.sfu import JanusSession
from tests.netlab import ensure_packages
from tests.servers import free_port

LIBDIR = Path("/usr/lib/x86_64-linux-gnu/janus")


def janus_ensure() -> str:
    """The janus binary, installed with janus-tools when missing (or while another test
    process is still installing them: their files appear one by one)."""
    ensure_packages("janus", "janus-tools")
    binary = shutil.which("janus")
    assert binary is not None
    return binary


def _libdir() -> Path:
    for candidate in (LIBDIR, *Path("/usr/lib").glob("*/janus")):
        if (candidate / "plugins" / "libjanus_videoroom.so").exists():
            return candidate
    raise RuntimeError("Janus's VideoRoom plugin is not installed")


@dataclass
class JanusServer:
    """A running private Janus; :meth:`kill` stops it as a crash would."""

    folder: Path
    http_port: int
    ws_port: int
    token_secret: str
    admin_key: str
    proc: subprocess.Popen[bytes] | None = None

    @property
    def http_url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}/janus"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.ws_port}/"

    @property
    def rec_dir(self) -> Path:
        return self.folder / "recordings"

    @property
    def log_path(self) -> Path:
        return self.folder / "janus.log"

    def settings(self) -> dict[str, object]:
        """The platform's settings for this server."""
        return {
            "IOUV_JANUS_URL": self.http_url,
            "IOUV_JANUS_PUBLIC_URL": self.ws_url,
            "IOUV_JANUS_TOKEN_SECRET": self.token_secret,
            "IOUV_JANUS_ADMIN_KEY": self.admin_key,
            "IOUV_JANUS_REC_DIR": str(self.rec_dir),
        }

    def start(self, within: float = 30.0) -> None:
        self.proc = subprocess.Popen(
            [
                janus_ensure(),
                "-F",
                str(self.folder / "conf"),
                "-C",
                str(self.folder / "conf" / "janus.jcfg"),
            ],
            stdout=self.log_path.open("ab"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + within
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"janus exited: {self.log_path.read_text()[-2000:]}")
            try:
                request = urllib.request.Request(
                    f"{self.http_url}/info", headers={"Accept": "application/json"}
                )
                with urllib.request.urlopen(request, timeout=1) as response:
                    if json.loads(response.read()).get("janus") == "server_info":
                        return
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"janus did not answer within {within:g} s")
            time.sleep(0.1)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()


def janus_config(server: JanusServer) -> None:
    """Write the server's configuration: deploy/janus's files with the test's folders,
    ports and secrets."""
    lib = _libdir()
    conf = server.folder / "conf"
    for sub in ("plugins", "transports", "events", "loggers"):
        (server.folder / sub).mkdir(parents=True, exist_ok=True)
    conf.mkdir(exist_ok=True)
    server.rec_dir.mkdir(exist_ok=True)
    # Only what the platform uses is loaded: a plugin or transport folder of their own.
    (server.folder / "plugins" / "libjanus_videoroom.so").symlink_to(
        lib / "plugins" / "libjanus_videoroom.so"
    )
    for transport in ("libjanus_http.so", "libjanus_websockets.so"):
        (server.folder / "transports" / transport).symlink_to(lib / "transports" / transport)
    from tests.production import janus_rendered

    for name, text in janus_rendered(
        configs=conf,
        libdir=server.folder,
        http_port=server.http_port,
        ws_port=server.ws_port,
        token_secret=server.token_secret,
        admin_key=server.admin_key,
        rtp_ports=None,
    ).items():
        (conf / name).write_text(text)


@contextlib.contextmanager
def janus_server(folder: Path) -> Iterator[JanusServer]:
    """A private Janus in ``folder`` (its configuration, log and recordings), stopped at
    the end. Janus is installed first when missing (its plugins are configured before
    the server starts)."""
    janus_ensure()
    server = JanusServer(
        folder=folder,
        http_port=free_port(),
        ws_port=free_port(),
        token_secret=secrets.token_urlsafe(24),
        admin_key=secrets.token_urlsafe(24),
    )
    janus_config(server)
    server.start()
    try:
        yield server
    finally:
        server.stop()


class Spectator:
    """A headless spectator: subscribes to the vehicle's feed at Janus as a browser
    would (token, room, pin) and counts the RTP packets it receives. aiortc decodes
    every frame it receives; they are taken from the track and dropped, so that a
    spectator's memory stays flat however long it watches."""

    def __init__(self, url: str, *, token: str | None, room: int, pin: str, feed: int) -> None:
        self.url, self.token, self.room, self.pin, self.feed = url, token, room, pin, feed
        self.janus: JanusSession | None = None
        self.pc: RTCPeerConnection | None = None
        self._draining: set[asyncio.Task[None]] = set()

    async def watch(self) -> None:
        """Join and start; raises JanusError when Janus refuses."""
        self.janus = janus = JanusSession(self.url, token=self.token)
        await janus.__aenter__()
        handle = await janus.attach()
        _, jsep = await handle.request(
            {
                "request": "join",
                "ptype": "subscriber",
                "room": self.room,
                "pin": self.pin,
                "streams": [{"feed": self.feed}],
            }
        )
        assert jsep is not None and jsep["type"] == "offer"
        self.pc = pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))

        @pc.on("track")
        def on_track(track: MediaStreamTrack) -> None:
            task = asyncio.ensure_future(self._drain(track))
            self._draining.add(task)
            task.add_done_callback(self._draining.discard)

        await pc.setRemoteDescription(RTCSessionDescription(jsep["sdp"], "offer"))
        await pc.setLocalDescription(await pc.createAnswer())
        await handle.request(
            {"request": "start"}, jsep={"type": "answer", "sdp": pc.localDescription.sdp}
        )

    @staticmethod
    async def _drain(track: MediaStreamTrack) -> None:
        with contextlib.suppress(Exception):  # the track ended (MediaStreamError)
            while True:
                await track.recv()

    async def packets(self) -> int:
        """RTP packets received so far."""
        return sum(s.packetsReceived for s in await self._inbound())

    async def _inbound(self) -> list[Any]:
        if self.pc is None:
            return []
        stats = await self.pc.getStats()
        return [s for s in stats.values() if s.type == "inbound-rtp"]

    async def close(self) -> None:
        if self.pc is not None:
            await self.pc.close()
        if self.janus is not None:
            await self.janus.close()
        for task in list(self._draining):
            task.cancel()
