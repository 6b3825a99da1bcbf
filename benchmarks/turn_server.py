"""coturn as a child process on loopback, for benchmarks and tests that need a TURN server.

    with turn_server(log_dir=Path("var/logs")) as turn:
        servers = turn.ice_servers("session-id")  # TURN REST credentials, minted here
        ...

One ``turnserver`` (coturn, Debian package ``coturn``) listens for STUN and TURN on one
UDP/TCP port of ``127.0.0.1`` (no TLS/DTLS), allocates relays on ``127.0.0.1`` and may
relay to loopback peers only: everything stays on this machine. Credentials follow the
TURN REST scheme (``use-auth-secret``) that the platform's :mod:`services.sessions.ice` mints with
``IOUV_TURN_SECRET``; :meth:`TurnServer.ice_servers` mints them with the same function.

:func:`turn_server` returns once the server answers a STUN binding request, and stops the
process on exit (SIGTERM, then SIGKILL). On Linux the child also gets SIGKILL when the
thread that started it dies, so a killed benchmark leaves no coturn behind: start it
from a thread that lives as long as it should (the main thread, not ``asyncio.to_thread``).
:func:`turnserver_missing` says why none can be started (coturn not installed).
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class TurnServerError(Exception):
    """coturn could not be started or did not answer; the message says why."""


@dataclass(frozen=True)
class TurnServer:
    """A running coturn: STUN and TURN over UDP (and TCP) on ``host:port``."""

    host: str
    port: int
    secret: str
    realm: str
    log_path: Path
    process: subprocess.Popen[bytes]

    @property
    def stun_urls(self) -> list[str]:
        return [f"stun:{self.host}:{self.port}"]

    @property
    def turn_urls(self) -> list[str]:
        return [self.url()]

    @property
    def urls(self) -> list[str]:
        """``stun:`` and ``turn:...?transport=udp`` URLs, in that order."""
        return [*self.stun_urls, *self.turn_urls]

    def url(self, *, port: int | None = None) -> str:
        """The ``turn:`` URL (UDP); ``port`` replaces the server's own, e.g. to go
        through a :class:`~benchmarks.delay_proxy.UdpDelayProxy` in front of it."""
        return f"turn:{self.host}:{port or self.port}?transport=udp"

    def credentials(self, name: str, *, ttl_s: int = 3600) -> tuple[str, str]:
        """(username, password) for ``name`` (no ``:``), valid ``ttl_s`` seconds: the
        TURN REST scheme of :func:`services.sessions.ice.turn_credentials`."""
        from services.sessions.ice import turn_credentials

        return turn_credentials(self.secret, name, ttl_s=ttl_s)

    def ice_servers(
        self, name: str, *, port: int | None = None, ttl_s: int = 3600
    ) -> list[dict[str, Any]]:
        """One RTCIceServer-shaped dict: this server's TURN URL (or ``port``'s, see
        :meth:`url`) with fresh credentials for ``name``."""
        username, credential = self.credentials(name, ttl_s=ttl_s)
        return [{"urls": [self.url(port=port)], "username": username, "credential": credential}]

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def allocations(self) -> int:
        """TURN allocations granted so far (successful ALLOCATE requests in the log)."""
        return len(re.findall(r"ALLOCATE processed, success", self.log()))

    def version(self) -> str:
        """coturn's version as its log states it, or ``unknown``."""
        found = re.search(r"Version Coturn-([\w.\-]+)", self.log())
        return found.group(1) if found else "unknown"


def turnserver_missing() -> str | None:
    """None when coturn can be started here, else why not."""
    if not sys.platform.startswith("linux"):
        return "the TURN server helper runs coturn on Linux only"
    if shutil.which("turnserver") is None:
        return "coturn is not installed (apt-get install coturn)"
    return None


def free_udp_tcp_port(host: str = "127.0.0.1") -> int:
    """A port free for both UDP and TCP on ``host`` (coturn listens on both)."""
    for _ in range(50):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            udp.bind((host, 0))
            port = int(udp.getsockname()[1])
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
                try:
                    tcp.bind((host, port))
                except OSError:
                    continue
                return port
    raise TurnServerError(f"no free UDP+TCP port on {host}")


#: Put before a child's command line: the child is SIGKILLed when the thread that started
#: it dies (PR_SET_PDEATHSIG, kept across exec). Set by util-linux's setpriv, not by a
#: preexec_fn: Python code between fork and exec in a threaded process can wait for
#: ever on a lock another thread held at the fork (seen: a network lab's child parked
#: on a futex, and its test with it, under Python 3.12).
DIE_WITH_PARENT: tuple[str, ...] = (
    ("setpriv", "--pdeathsig", "KILL", "--") if shutil.which("setpriv") else ()
)


def stun_answers(host: str, port: int, *, timeout_s: float = 0.2) -> bool:
    """Whether a STUN binding request to ``host:port`` is answered within ``timeout_s``."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout_s)
        txid = os.urandom(12)
        # Binding request: type 0x0001, length 0, magic cookie, transaction id.
        sock.sendto(b"\x00\x01\x00\x00\x21\x12\xa4\x42" + txid, (host, port))
        with contextlib.suppress(TimeoutError, ConnectionRefusedError):
            data = sock.recv(2048)
            return data[:2] == b"\x01\x01" and data[8:20] == txid
    return False


def _stop(proc: subprocess.Popen[bytes], timeout_s: float = 5.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def turn_server(
    *,
    log_dir: Path,
    secret: str | None = None,
    host: str = "127.0.0.1",
    port: int | None = None,
    realm: str = "iouv.bench",
    relay_ports: tuple[int, int] = (40000, 40999),
    peers: str | None = None,
    pidfile: Path | None = None,
    ready_timeout_s: float = 10.0,
) -> Iterator[TurnServer]:
    """Run coturn on ``host`` until the block ends; yields it once it answers STUN.
    ``secret`` (default: a random one) is its ``static-auth-secret``; ``relay_ports``
    the range its relays use (ports in use are skipped); ``peers`` the only addresses it
    relays to (``A`` or ``A-B``; default ``host`` alone, loopback peers allowed when it
    is a loopback address). Its log, user database and pidfile (default: named after the
    port) go to ``log_dir``. Raises TurnServerError when coturn is missing, exits, or
    does not answer within ``ready_timeout_s``."""
    missing = turnserver_missing()
    if missing is not None:
        raise TurnServerError(missing)
    secret = secret or secrets.token_hex(16)
    port = port or free_udp_tcp_port(host)
    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"turnserver-{port}.log"
    log_path.unlink(missing_ok=True)
    argv = [
        "turnserver",
        "-n",  # no config file: everything is on this command line
        "--listening-ip", host,
        "--relay-ip", host,
        "--listening-port", str(port),
        "--min-port", str(relay_ports[0]),
        "--max-port", str(relay_ports[1]),
        "--use-auth-secret",
        "--static-auth-secret", secret,
        "--realm", realm,
        "--fingerprint",
        "--no-tls",
        "--no-dtls",
        "--no-cli",
        "--no-rfc5780",
        "--no-software-attribute",
        # Relays reach the peers named, nothing else (coturn refuses some special
        # ranges by default, and documentation ranges are not "public" to every version).
        *(["--allow-loopback-peers"] if host.startswith("127.") else []),
        f"--allowed-peer-ip={peers or host}",
        "--denied-peer-ip=0.0.0.0-255.255.255.255",
        "--no-multicast-peers",
        "--userdb", str(log_dir / f"turndb-{port}"),
        "--pidfile", str(pidfile or log_dir / f"turnserver-{port}.pid"),
        "--log-file", str(log_path),
        "--simple-log",
        "--no-stdout-log",
        "--verbose",
    ]  # fmt: skip
    proc = subprocess.Popen(
        [*DIE_WITH_PARENT, *argv],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    turn = TurnServer(
        host=host, port=port, secret=secret, realm=realm, log_path=log_path, process=proc
    )
    try:
        deadline = time.monotonic() + ready_timeout_s
        while not stun_answers(host, port):
            if proc.poll() is not None:
                raise TurnServerError(
                    f"turnserver exited with {proc.returncode}:\n{turn.log()[-2000:]}"
                )
            if time.monotonic() > deadline:
                raise TurnServerError(
                    f"turnserver did not answer STUN on {host}:{port} in {ready_timeout_s:g} s"
                )
        yield turn
    finally:
        _stop(proc)
