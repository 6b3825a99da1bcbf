"""nginx as the front proxy of the benchmarks and tests: one address, backends by path.

    python -m benchmarks.nginx_proxy --listen 127.0.0.1:8000 \\
        --route /ws/agent/=127.0.0.1:8001 --default 127.0.0.1:8002

The platform runs as several daphne processes behind one address, as a deployment does
behind nginx: the agents' uplinks (``/ws/agent/``) go to one process, browsers and API
programs to another, both sharing PostgreSQL and Redis. This module runs Debian's nginx
(``apt-get install nginx`` if it is missing) with a configuration it writes into a
private prefix directory: no system file is read or changed, and no root is needed to
run it. :class:`NginxProxy` is the async context manager the tests use;
``benchmarks.scale`` starts it as a child process with a log.

Routing is nginx's: a ``location`` per path prefix, the longest matching prefix wins
(:meth:`Routes.backend_for` states the same rule), everything else goes to the default
backend. Routing is per **request**, WebSocket upgrades included (``proxy_http_version
1.1`` and the ``Upgrade``/``Connection`` headers). The request reaches the backend with
the client's ``Host`` (so the URLs daphne builds, such as a task's relay URL, point back
at the proxy), ``X-Forwarded-For`` and ``X-Forwarded-Proto``. docs/operations.md has
the production configuration, with TLS.

With :class:`Tls` (``--tls-certificate`` and ``--tls-key``) nginx terminates TLS, as in
production: the proxy serves ``https://`` and ``wss://`` and tells the backends
``X-Forwarded-Proto: https``; ``redirect_port`` (``--redirect-port``) adds a plain-http
listener on the same host that answers every request with a 301 to the https one, as
production's port 80 does. tests/integration/test_https_portal_browser.py runs the
portal that way.

On a machine with systemd, Debian's package also starts the system's own nginx (port
80, the default site); this module never uses or touches it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import re
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import BinaryIO, Self

from tests.ports import free_port as tests_free_port

log = logging.getLogger(__name__)

#: Where Debian's package puts the binary; ``IOUV_NGINX`` names another one.
NGINX = Path(os.environ.get("IOUV_NGINX", "/usr/sbin/nginx"))
#: The largest request body the platform accepts anywhere: Django's default
#: ``DATA_UPLOAD_MAX_MEMORY_SIZE`` (2.5 MiB, pages and the admin; iouv/settings.py does
#: not change it). The API's own limit is tighter (``MAX_BODY_BYTES``, 64 KiB) and the
#: platform answers it with its JSON ``413 payload_too_large``: nginx must let such a
#: body through rather than answer first with its own HTML page.
CLIENT_MAX_BODY_BYTES = 2_621_440
#: No proxy timeout may end a live WebSocket before the platform does: daphne pings a
#: WebSocket silent for 20 s and closes it if no answer comes within 30 s, and agents
#: heartbeat every 2 s, so a silent hour means a stuck backend, not an idle user. API
#: requests finish in well under a second and never come near it.
PROXY_TIMEOUT_S = 3600
#: Open files nginx leaves for itself (listening socket, logs, temp files) out of its
#: limit when sizing ``worker_connections``.
RESERVED_FILES = 64
START_TIMEOUT_S = 30.0
STOP_GRACE_S = 10.0


class NginxUnavailable(RuntimeError):
    """nginx is missing and could not be installed (no apt-get, no root, apt failed)."""


@dataclass(frozen=True)
class Backend:
    """An address: where requests are forwarded, or where the proxy listens."""

    host: str
    port: int

    @classmethod
    def parse(cls, text: str, *, any_port: bool = False) -> Backend:
        """``host:port`` (``[::1]:8000`` for IPv6); port 0 only with ``any_port`` (a
        listening address: any free port). Raises ValueError otherwise."""
        host, sep, port = text.rpartition(":")
        low = 0 if any_port else 1
        if not sep or not host or not port.isdigit() or not low <= int(port) < 65536:
            raise ValueError(f"expected host:port, got {text!r}")
        return cls(host.strip("[]"), int(port))

    def __str__(self) -> str:
        """``host:port`` as nginx writes it (IPv6 in brackets)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


#: Prefixes are written into the configuration unquoted: only URL path characters.
_PREFIX = re.compile(r"/[A-Za-z0-9._~%/-]*")


@dataclass(frozen=True)
class Rule:
    """Requests whose path starts with ``prefix`` go to ``backend``."""

    prefix: str
    backend: Backend

    def __post_init__(self) -> None:
        if not _PREFIX.fullmatch(self.prefix):
            raise ValueError(f"a prefix is a URL path starting with /, got {self.prefix!r}")

    @classmethod
    def parse(cls, text: str) -> Rule:
        """``/path/prefix=host:port``; raises ValueError otherwise."""
        prefix, sep, target = text.partition("=")
        if not sep:
            raise ValueError(f"expected /prefix=host:port, got {text!r}")
        return cls(prefix, Backend.parse(target))


@dataclass(frozen=True)
class Routes:
    """The routing table: prefix rules (longest match wins) and a default backend."""

    default: Backend
    rules: Sequence[Rule] = ()

    def __post_init__(self) -> None:
        prefixes = [rule.prefix for rule in self.rules]
        # nginx refuses two locations with one prefix, and "/" is the default's.
        if len(set(prefixes)) != len(prefixes) or "/" in prefixes:
            raise ValueError(f"prefixes must be distinct and not '/', got {prefixes}")

    def backend_for(self, path: str) -> Backend:
        """The backend nginx picks for a request path (query string ignored). One case
        apart: nginx answers a path equal to a prefix ending in ``/`` but without that
        slash (``/ws/agent``) itself, with a redirect to the prefix."""
        path = path.split("?", 1)[0]
        matches = [rule for rule in self.rules if path.startswith(rule.prefix)]
        if not matches:
            return self.default
        return max(matches, key=lambda rule: len(rule.prefix)).backend

    @classmethod
    def parse(cls, route: Sequence[str], default: str) -> Routes:
        """A routing table from CLI-style texts; raises ValueError naming a bad one."""
        return cls(default=Backend.parse(default), rules=[Rule.parse(r) for r in route])


@dataclass(frozen=True)
class Tls:
    """TLS at the proxy: ``certificate`` is the PEM chain (the server's certificate
    first, then the intermediates), ``key`` its private key (PEM, unencrypted)."""

    certificate: Path
    key: Path

    def __post_init__(self) -> None:
        for path in (self.certificate, self.key):
            # Written into the configuration unquoted.
            if not _CONFIG_PATH.fullmatch(str(path)):
                raise ValueError(f"a TLS file path without spaces or ';', got {str(path)!r}")


#: File paths are written into the configuration unquoted.
_CONFIG_PATH = re.compile(r"[^\s;{}'\"\\]+")


@dataclass(frozen=True)
class AccessEntry:
    """One request in nginx's access log (a WebSocket is logged when it ends)."""

    method: str
    uri: str
    status: int
    upstream: str  # "127.0.0.1:8001"; "-" when nginx answered itself


def free_port(host: str = "127.0.0.1") -> int:
    """A port nothing listens on right now: under the tests, from the worker's own range
    (tests.ports), since the kernel's pick is in the range its outgoing connections also
    draw from and another process may take it before nginx binds it."""
    if ":" not in host:
        return tests_free_port(host)
    with socket.socket(socket.AF_INET6) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def raise_open_files_limit() -> int:
    """Raise this process's open-file limit to its hard limit (a proxied connection
    costs nginx two descriptors, and nginx inherits the limit); returns the new soft
    limit."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


# --------------------------------------------------------------------------------------
# Finding and installing nginx
# --------------------------------------------------------------------------------------


def nginx_install() -> None:
    """Install Debian's ``nginx`` package (as bin/install-chromium does Chromium):
    quiet unless it fails, with sudo when not root. Raises NginxUnavailable."""
    if shutil.which("apt-get") is None:
        raise NginxUnavailable(f"no apt-get here; install nginx at {NGINX} by hand")
    sudo: list[str] = []
    if os.geteuid() != 0:
        if shutil.which("sudo") is None:
            raise NginxUnavailable("must run as root (or with sudo) to install nginx")
        sudo = ["sudo", "-n"]  # never a password prompt: a test would hang on it
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    # Another process installing at the same time holds dpkg's lock: wait for it.
    wait = ["-o", "DPkg::Lock::Timeout=120"]
    log.info("installing Debian's nginx with apt-get")
    for args in (
        [*sudo, "apt-get", *wait, "update", "-qq"],
        [*sudo, "apt-get", *wait, "install", "-y", "-qq", "--no-install-recommends", "nginx"],
    ):
        done = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            tail = "\n".join((done.stdout + done.stderr).splitlines()[-20:])
            raise NginxUnavailable(f"{' '.join(args)} failed ({done.returncode}):\n{tail}")
    if not os.access(NGINX, os.X_OK):
        raise NginxUnavailable(f"nginx installed, but {NGINX} is still missing")


def _dpkg_installing(package: str) -> bool:
    """Whether dpkg knows ``package`` but has not finished installing it: another
    process is installing it now, and its files (the binary first, the configuration it
    includes later) are still appearing. :func:`nginx_install` then waits for dpkg's
    lock and finds it done."""
    if shutil.which("dpkg-query") is None:
        return False
    status = subprocess.run(
        ["dpkg-query", "-W", "-f=${Status}", package], capture_output=True, text=True
    ).stdout.strip()
    return bool(status) and status != "install ok installed" and "not-installed" not in status


def nginx_binary(*, install: bool = True) -> Path:
    """The nginx binary, installed first if it is missing and ``install`` is true.
    Idempotent. Raises NginxUnavailable."""
    if not os.access(NGINX, os.X_OK) or _dpkg_installing("nginx"):
        if not install:
            raise NginxUnavailable(f"no nginx at {NGINX}")
        nginx_install()
    return NGINX


# --------------------------------------------------------------------------------------
# The configuration
# --------------------------------------------------------------------------------------


def worker_connections(open_files: int | None = None) -> int:
    """Connections nginx may hold: each proxied WebSocket takes two (client and
    backend), so 20,000 open files carry about 10,000 agents and browsers."""
    limit = open_files if open_files is not None else resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    return max(512, min(65536, limit - RESERVED_FILES))


def render_config(
    routes: Routes,
    *,
    listen: Backend,
    prefix: Path,
    connections: int | None = None,
    tls: Tls | None = None,
    redirect: Backend | None = None,
) -> str:
    """The nginx.conf that serves ``listen`` and routes by ``routes``, keeping every
    file nginx writes (pid, logs, temporary bodies) under ``prefix``. With ``tls``,
    ``listen`` speaks TLS; ``redirect`` (only with ``tls``) is a plain-http address
    that sends every request to the same path on ``listen``'s https."""
    if redirect is not None and tls is None:
        raise ValueError("a redirect to https needs TLS")
    backends = list(dict.fromkeys([routes.default, *(rule.backend for rule in routes.rules)]))
    upstream = {backend: f"backend_{i}" for i, backend in enumerate(backends)}
    temp = prefix / "temp"
    lines = [
        "# Written by benchmarks/nginx_proxy.py; nginx -p PREFIX -c THIS -e stderr.",
        # In the foreground as the caller's child, so the caller sees it exit.
        "daemon off;",
        # One process that does everything: the pid the caller holds is the one that
        # works (benchmarks.scale measures its CPU and memory) and stopping it leaves
        # nothing behind; run as root, a master would also hand the work to workers as
        # "nobody", who cannot enter this private prefix. worker_processes and
        # worker_rlimit_nofile are a master's settings: nginx inherits the caller's
        # open-file limit instead (raise_open_files_limit), and one process is plenty
        # for a proxy beside a platform that uses every core of a small machine.
        "master_process off;",
        "worker_processes 1;",
        f"pid {prefix / 'nginx.pid'};",
        "error_log stderr notice;",
        "events {",
        f"    worker_connections {connections or worker_connections()};",
        "}",
        "http {",
        "    log_format routed '$request_method\\t$request_uri\\t$status\\t$upstream_addr';",
        f"    access_log {prefix / 'access.log'} routed;",
        f"    client_body_temp_path {temp / 'client_body'};",
        f"    proxy_temp_path {temp / 'proxy'};",
        f"    fastcgi_temp_path {temp / 'fastcgi'};",
        f"    uwsgi_temp_path {temp / 'uwsgi'};",
        f"    scgi_temp_path {temp / 'scgi'};",
        "    server_tokens off;",
        # A WebSocket handshake asks the backend to upgrade; any other request is
        # sent with no Connection header, so the connection to the backend is kept
        # alive (the upstreams' keepalive) instead of opened per request.
        "    map $http_upgrade $connection_upgrade {",
        "        default upgrade;",
        "        '' '';",
        "    }",
    ]
    for backend, name in upstream.items():
        lines += [f"    upstream {name} {{", f"        server {backend};", "        keepalive 16;"]
        lines += ["    }"]
    if redirect is not None:
        # $host is the name the client asked for, without its port: the https port is
        # written here unless it is the default.
        port = "" if listen.port == 443 else f":{listen.port}"
        lines += [
            "    server {",
            f"        listen {redirect};",
            f"        return 301 https://$host{port}$request_uri;",
            "    }",
        ]
    lines += [
        "    server {",
        # A reconnect storm (every agent at once after a restart) queues here.
        f"        listen {listen}{' ssl' if tls else ''} backlog=4096;",
    ]
    if tls is not None:
        lines += [
            f"        ssl_certificate {tls.certificate};",
            f"        ssl_certificate_key {tls.key};",
            "        ssl_protocols TLSv1.2 TLSv1.3;",
        ]
    lines += [
        "        proxy_http_version 1.1;",
        "        proxy_set_header Upgrade $http_upgrade;",
        "        proxy_set_header Connection $connection_upgrade;",
        # With its port: daphne builds URLs (a task's relay URL) from it.
        "        proxy_set_header Host $http_host;",
        "        proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;",
        "        proxy_set_header X-Forwarded-Proto $scheme;",
        f"        proxy_read_timeout {PROXY_TIMEOUT_S}s;",
        f"        proxy_send_timeout {PROXY_TIMEOUT_S}s;",
        # WebSockets are never buffered; API answers are (nginx's default), which
        # frees daphne's request thread at once even for a slow client.
        f"        client_max_body_size {CLIENT_MAX_BODY_BYTES};",
    ]
    for rule in routes.rules:
        lines += [
            f"        location {rule.prefix} {{ proxy_pass http://{upstream[rule.backend]}; }}"
        ]
    lines += [
        f"        location / {{ proxy_pass http://{upstream[routes.default]}; }}",
        "    }",
        "}",
    ]
    return "\n".join(lines) + "\n"


def _command(binary: Path, prefix: Path, *extra: str) -> list[str]:
    # -e stderr: nginx's start-up messages, before it reads the configuration, would
    # otherwise go to /var/log/nginx/error.log (unwritable for a normal user).
    conf = prefix / "nginx.conf"
    return [str(binary), "-p", f"{prefix}/", "-c", str(conf), "-e", "stderr", *extra]


def config_check(prefix: Path, binary: Path | None = None) -> str:
    """Run ``nginx -t`` on ``prefix``'s nginx.conf; returns nginx's verdict, raises
    RuntimeError with it if the configuration is refused."""
    done = subprocess.run(
        _command(binary or nginx_binary(), prefix, "-t"),
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"nginx -t refused {prefix / 'nginx.conf'}:\n{done.stderr}")
    return done.stderr


# --------------------------------------------------------------------------------------
# Running it
# --------------------------------------------------------------------------------------


def _open_append(path: Path) -> BinaryIO:
    # A small local file, opened once per start: no need for a thread.
    return open(path, "ab")


async def _accepts(host: str, port: int) -> bool:
    try:
        _, writer = await asyncio.wait_for(asyncio.open_connection(host, port), 2)
    except (OSError, TimeoutError):
        return False
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return True


class NginxProxy:
    """nginx routing by ``routes``, as an async context manager: listens on
    ``host:port`` (port 0: a free port, see :attr:`port`) once entered, stopped on exit.
    With ``tls`` it speaks https and wss there; ``redirect_port`` (0: a free port, see
    :attr:`redirect_url`) then also listens for plain http on ``host`` and redirects
    every request to https.

    ``prefix`` is the directory for the configuration, pid, access log and temporary
    files (default: a temporary directory, removed on exit); ``log`` receives nginx's
    error log (default: ``prefix/error.log``).
    """

    def __init__(
        self,
        routes: Routes,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        prefix: Path | None = None,
        log: Path | None = None,
        tls: Tls | None = None,
        redirect_port: int | None = None,
    ) -> None:
        if redirect_port is not None and tls is None:
            raise ValueError("a redirect to https needs TLS")
        self.routes = routes
        self.host = host
        self.port = port
        # nginx would take a relative path from its prefix, not from here.
        self.tls = tls and Tls(tls.certificate.resolve(), tls.key.resolve())
        self.redirect_port = redirect_port
        self._own_prefix = prefix is None
        self.prefix = prefix or Path(tempfile.mkdtemp(prefix="iouv-nginx-"))
        self.log_path = log or self.prefix / "error.log"
        self.process: asyncio.subprocess.Process | None = None

    @property
    def url(self) -> str:
        """``http://host:port``, or ``https://host:port`` with TLS."""
        return f"{'https' if self.tls else 'http'}://{Backend(self.host, self.port)}"

    @property
    def redirect_url(self) -> str | None:
        """``http://host:port`` of the redirect to https, if there is one."""
        if self.redirect_port is None:
            return None
        return f"http://{Backend(self.host, self.redirect_port)}"

    @property
    def access_log_path(self) -> Path:
        return self.prefix / "access.log"

    def write_config(self) -> Path:
        """Write nginx.conf into the prefix (choosing the port if it is 0); its path."""
        if not self.port:
            self.port = free_port(self.host)
        if self.redirect_port == 0:
            self.redirect_port = free_port(self.host)
        (self.prefix / "temp").mkdir(parents=True, exist_ok=True)
        path = self.prefix / "nginx.conf"
        listen = Backend(self.host, self.port)
        redirect = None if self.redirect_port is None else Backend(self.host, self.redirect_port)
        path.write_text(
            render_config(
                self.routes, listen=listen, prefix=self.prefix, tls=self.tls, redirect=redirect
            )
        )
        return path

    async def start(self) -> None:
        """Start nginx; returns once it accepts connections. Raises RuntimeError, with
        nginx's log, if it does not within START_TIMEOUT_S (or NginxUnavailable)."""
        binary = await asyncio.to_thread(nginx_binary)
        raise_open_files_limit()  # before the fork: nginx inherits it
        self.write_config()
        pid_file = self.prefix / "nginx.pid"
        pid_file.unlink(missing_ok=True)
        with _open_append(self.log_path) as log_file:  # nginx keeps its own descriptor
            self.process = await asyncio.create_subprocess_exec(
                *_command(binary, self.prefix),
                stdin=asyncio.subprocess.DEVNULL,
                stdout=log_file,
                stderr=log_file,
            )
        deadline = time.monotonic() + START_TIMEOUT_S
        # nginx writes its pid file after binding the listening socket: a connection
        # accepted before that could be another program's on the same port.
        while not (self._pid_written(pid_file) and await self._all_accept()):
            if self.process.returncode is not None or time.monotonic() > deadline:
                await self._terminate()
                output = self.log_path.read_text(errors="replace")[-2000:]
                await self.stop()
                raise RuntimeError(f"nginx did not start on {self.host}:{self.port}: {output}")
            await asyncio.sleep(0.02)
        log.info("nginx (pid %d) on %s", self.process.pid, self.url)

    async def _all_accept(self) -> bool:
        ports = [self.port] if self.redirect_port is None else [self.port, self.redirect_port]
        return all([await _accepts(self.connect_host, port) for port in ports])

    @property
    def connect_host(self) -> str:
        """Where to connect to reach the proxy (a wildcard address means loopback)."""
        return {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(self.host, self.host)

    def _pid_written(self, pid_file: Path) -> bool:
        assert self.process is not None
        try:
            return pid_file.read_text().strip() == str(self.process.pid)
        except OSError:
            return False

    async def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """Stop nginx (SIGTERM, then SIGKILL after ``grace_s``) and remove a temporary
        prefix. Idempotent."""
        await self._terminate(grace_s)
        if self._own_prefix:
            shutil.rmtree(self.prefix, ignore_errors=True)

    async def _terminate(self, grace_s: float = STOP_GRACE_S) -> None:
        # SIGTERM, not SIGQUIT: a graceful stop would wait for every WebSocket to end,
        # while a restarted proxy must drop them all at once, as a crashed one would.
        proc = self.process
        if proc is not None and proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(proc.wait(), grace_s)
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                await proc.wait()

    def requests(self) -> list[AccessEntry]:
        """The requests nginx has logged so far, oldest first."""
        try:
            text = self.access_log_path.read_text(errors="replace")
        except FileNotFoundError:
            return []
        entries = []
        for line in text.splitlines():
            method, uri, status, upstream = line.split("\t")
            entries.append(AccessEntry(method, uri, int(status), upstream))
        return entries

    async def __aenter__(self) -> Self:
        try:
            await self.start()
        except BaseException:
            await self.stop()
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()


# --------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------


async def _serve(proxy: NginxProxy) -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with proxy:
        also = f" (and {proxy.redirect_url}, redirecting)" if proxy.redirect_url else ""
        print(f"nginx listening on {proxy.url}{also}, files in {proxy.prefix}", flush=True)
        assert proxy.process is not None
        await asyncio.wait(
            [asyncio.create_task(stop.wait()), asyncio.create_task(proxy.process.wait())],
            return_when=asyncio.FIRST_COMPLETED,
        )


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.nginx_proxy",
        description="Run nginx routing requests by path prefix to backends.",
    )
    parser.add_argument("--listen", default="127.0.0.1:8000", help="host:port (port 0: any)")
    parser.add_argument(
        "--route",
        action="append",
        default=[],
        metavar="/PREFIX=HOST:PORT",
        help="requests whose path starts with PREFIX go to HOST:PORT (repeatable)",
    )
    parser.add_argument("--default", required=True, metavar="HOST:PORT", help="all the rest")
    parser.add_argument("--prefix", type=Path, help="directory for nginx's files (default: temp)")
    parser.add_argument(
        "--tls-certificate",
        type=Path,
        metavar="PEM",
        help="terminate TLS on --listen with this certificate chain (needs --tls-key)",
    )
    parser.add_argument("--tls-key", type=Path, metavar="PEM", help="the certificate's key")
    parser.add_argument(
        "--redirect-port",
        type=int,
        metavar="PORT",
        help="with TLS: also listen for plain http on this port (0: any) and redirect to https",
    )
    parser.add_argument(
        "--print-config", action="store_true", help="print the configuration and exit"
    )
    args = parser.parse_args(argv)
    if (args.tls_certificate is None) != (args.tls_key is None):
        parser.error("--tls-certificate and --tls-key go together")
    if args.redirect_port is not None and args.tls_certificate is None:
        parser.error("--redirect-port needs TLS (--tls-certificate and --tls-key)")
    if args.redirect_port is not None and not 0 <= args.redirect_port < 65536:
        parser.error(f"--redirect-port: not a port: {args.redirect_port}")
    try:
        listen = Backend.parse(args.listen, any_port=True)
        routes = Routes.parse(args.route, args.default)
        tls = None
        if args.tls_certificate is not None:
            tls = Tls(args.tls_certificate, args.tls_key)
    except ValueError as exc:
        parser.error(str(exc))
    proxy = NginxProxy(
        routes,
        host=listen.host,
        port=listen.port,
        prefix=args.prefix,
        tls=tls,
        redirect_port=args.redirect_port,
    )
    if args.print_config:
        sys.stdout.write(proxy.write_config().read_text())
        if args.prefix is None:
            shutil.rmtree(proxy.prefix)
        return
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    asyncio.run(_serve(proxy))


if __name__ == "__main__":
    main()
