"""The production shape as the tests run it: the very files production uses (``deploy/``),
with the test's own ports, certificate and folders put in.

* :func:`units_rendered`: the systemd units with this checkout and its virtualenv in
  place of ``/opt/iouv`` (for ``systemd-analyze verify``);
* :func:`nginx_site`: ``deploy/nginx/iouv.conf`` with the test's upstream ports,
  listening addresses, certificate and static folder; :func:`nginx_main` wraps it in a
  main configuration whose every file (pid, logs, temporary bodies) lives in a private
  prefix, so no system file is read or written;
* :class:`ProductionShape`: the platform run that way: gunicorn's HTTP processes and
  uvicorn's WebSocket processes (each restartable, as a deploy restarts them), nginx in
  front with TLS, the Celery worker and beat. By default every process is on this
  machine's loopback; with ``hosts`` (:class:`Host`: e.g. the machines of a
  tests.netlab lab) each host runs its own HTTP and WebSocket processes, on the ports
  production's units use, and nginx spreads over all of them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import ssl
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from django.conf import settings

from benchmarks import scale_topology
from benchmarks.nginx_proxy import nginx_binary
from tests.servers import ROOT, _test_database_url, celery_worker_process, free_port
from tests.tls import Certificates, certificates_make

DEPLOY = ROOT / "deploy"
SITE = DEPLOY / "nginx" / "iouv.conf"
UNITS = DEPLOY / "systemd"


def units_rendered(into: Path) -> list[Path]:
    """The units of ``deploy/systemd`` written to ``into`` with this checkout (and its
    ``.venv``) where production has ``/opt/iouv``, and each template once instantiated
    (``iouv-web@8001.service``...): what ``systemd-analyze verify`` can check here."""
    written = []
    for unit in sorted(UNITS.iterdir()):
        text = unit.read_text().replace("/opt/iouv", str(ROOT))
        names = [unit.name]
        if unit.name.endswith("@.service"):
            base = unit.name.removesuffix("@.service")
            names = [f"{base}@{8001 if base == 'iouv-web' else 8101}.service"]
        for name in names:
            (into / name).write_text(text)
            written.append(into / name)
    return written


def nginx_site(
    *,
    web: Sequence[int | str],
    ws: Sequence[int | str],
    https: int,
    http: int,
    certificates: Certificates,
    static_root: Path,
    server_options: str = "max_fails=0",
    upstream_keepalive: bool = True,
) -> str:
    """``deploy/nginx/iouv.conf`` as :func:`benchmarks.scale_topology.nginx_site`
    renders it (the scale benchmark runs the same), with ``certificates``' chain and
    key."""
    return scale_topology.nginx_site(
        web=web,
        ws=ws,
        https=https,
        http=http,
        certificate=certificates.chain,
        key=certificates.key,
        static_root=static_root,
        server_options=server_options,
        upstream_keepalive=upstream_keepalive,
        site=SITE,
    )


def nginx_main(prefix: Path, site: str) -> str:
    """A main nginx.conf around ``site`` keeping all nginx writes under ``prefix``: in
    the foreground, one process (the test holds its pid)."""
    temp = prefix / "temp"
    return "\n".join(
        [
            "daemon off;",
            "master_process off;",
            "worker_processes 1;",
            f"pid {prefix / 'nginx.pid'};",
            "error_log stderr notice;",
            "events { worker_connections 4096; }",
            "http {",
            "    include /etc/nginx/mime.types;",
            f"    access_log {prefix / 'access.log'};",
            f"    client_body_temp_path {temp / 'client_body'};",
            f"    proxy_temp_path {temp / 'proxy'};",
            f"    fastcgi_temp_path {temp / 'fastcgi'};",
            f"    uwsgi_temp_path {temp / 'uwsgi'};",
            f"    scgi_temp_path {temp / 'scgi'};",
            site,
            "}",
            "",
        ]
    )


def nginx_command(prefix: Path, *extra: str) -> list[str]:
    """nginx on ``prefix``'s nginx.conf (``-e stderr``: no system log at start-up)."""
    return [
        str(nginx_binary()),
        "-p",
        f"{prefix}/",
        "-c",
        str(prefix / "nginx.conf"),
        "-e",
        "stderr",
        *extra,
    ]


def nginx_prepared(prefix: Path, site: str) -> Path:
    """Write the main configuration around ``site`` into ``prefix``; returns its path."""
    (prefix / "temp").mkdir(parents=True, exist_ok=True)
    conf = prefix / "nginx.conf"
    conf.write_text(nginx_main(prefix, site))
    return conf


def _wait_http(url: str, *, context: ssl.SSLContext | None = None, within: float = 90.0) -> None:
    # 90 s, as tests.servers.PlatformServer: a saturated machine with the suite's other
    # workers takes tens of seconds to import Django in a process's workers.
    deadline = time.monotonic() + within
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5, context=context) as response:
                if response.status == 200:
                    return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{url} did not answer within {within:g} s") from None
            time.sleep(0.2)


class Process:
    """One server process on a fixed port, restartable as a deploy restarts it.

    ``host``: the address it listens on, where the test reaches it (a machine of a
    tests.netlab lab: ``command`` then runs in its namespace)."""

    def __init__(
        self,
        name: str,
        command: list[str],
        env: dict[str, str],
        port: int,
        *,
        host: str = "127.0.0.1",
    ) -> None:
        self.name = name
        self.command = command
        self.env = env
        self.port = port
        self.host = host
        self.proc: subprocess.Popen[bytes] | None = None
        self.log_path = Path(settings.VAR_DIR) / f"{name}-{port}.log"

    @property
    def address(self) -> str:
        """``host:port``, as nginx's upstream names it."""
        return f"{self.host}:{self.port}"

    def start(self) -> None:
        """Start it and return once it answers ``/healthz`` on its own port."""
        with open(self.log_path, "a") as log:
            self.proc = subprocess.Popen(
                self.command,
                cwd=ROOT,
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # kill() takes its worker processes too
            )
        try:
            _wait_http(f"http://{self.address}/healthz")
        except RuntimeError:
            raise RuntimeError(f"{self.name}: {self.log_path.read_text()[-2000:]}") from None

    def signal(self, number: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(number)

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM, as systemd stops it, and wait; SIGKILL past ``timeout``."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)

    def kill(self) -> None:
        """SIGKILL the process and its children (a gunicorn's workers), as a crash and
        then systemd's clean-up of the unit's control group would: no goodbye on any
        socket, requests in progress cut."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)

    def restart(self) -> None:
        """Stopped with SIGTERM, then started, as a deploy restarts it."""
        self.stop()
        self.start()

    def crash(self) -> None:
        """Killed, then started again, as systemd's ``Restart=always`` brings it back."""
        self.kill()
        self.start()


@dataclasses.dataclass(frozen=True)
class Host:
    """A machine the platform's processes run on: they listen on ``address`` (nginx
    reaches them there), their command lines start with ``prefix`` (e.g. ``ip netns exec
    <namespace>``), and ``env`` is added to their environment (e.g. a ``DATABASE_URL``
    that reaches PostgreSQL from there)."""

    name: str
    address: str
    prefix: tuple[str, ...] = ()
    env: Mapping[str, str] = dataclasses.field(default_factory=dict)


class ProductionShape:
    """The platform as deploy/ runs it, for one test; see the module docstring.

    ``base`` is the https address of nginx (``certificates.ca`` signs it), ``web`` and
    ``ws`` the HTTP and WebSocket processes (that many on each of ``hosts``, if given:
    ports 8001... and 8101..., as production's units); ``worker``: whether the Celery
    worker (with its beat) runs too, on this machine, as ``worker`` once running;
    ``server_options``, ``upstream_keepalive``: see :func:`nginx_site`."""

    def __init__(
        self,
        workdir: Path,
        *,
        web: int = 2,
        ws: int = 2,
        worker: bool = True,
        env: dict[str, str],
        hosts: Sequence[Host] = (),
        server_options: str = "max_fails=0",
        upstream_keepalive: bool = True,
    ) -> None:
        self.server_options = server_options
        self.upstream_keepalive = upstream_keepalive
        self.workdir = workdir
        self.with_worker = worker
        self.certificates = certificates_make(workdir / "tls")
        self.https, self.http = free_port(), free_port()
        self.base = f"https://127.0.0.1:{self.https}"
        self.env = {
            **os.environ,
            "DATABASE_URL": _test_database_url(),
            "DB_CONN_MAX_AGE": "0",
            "PYTHONUNBUFFERED": "1",
            "IOUV_FAST_PASSWORD_HASHER": "1",
            "BEHIND_PROXY": "1",
            "SERVE_STATIC": "0",
            "STATIC_ROOT": str(workdir / "static"),
            "ALLOWED_HOSTS": "127.0.0.1,localhost",
            **env,
        }
        places = [
            (host, [8001 + i for i in range(web)], [8101 + i for i in range(ws)]) for host in hosts
        ] or [
            (
                Host("local", "127.0.0.1"),
                [free_port() for _ in range(web)],
                [free_port() for _ in range(ws)],
            )
        ]
        self.web: list[Process] = []
        self.ws: list[Process] = []
        for host, web_ports, ws_ports in places:
            env_there = {**self.env, **host.env}
            if host.address != "127.0.0.1":
                # Its /healthz is asked for at its own address.
                env_there["ALLOWED_HOSTS"] += f",{host.address}"
            self.web += [
                Process(
                    "gunicorn" if not hosts else f"gunicorn-{host.name}",
                    [
                        *host.prefix, sys.executable, "-m", "gunicorn",
                        "-c", str(DEPLOY / "gunicorn.conf.py"), "--bind", f"{host.address}:{port}",
                        "--workers", "2", "iouv.wsgi:application",
                    ],
                    env_there,
                    port,
                    host=host.address,
                )
                for port in web_ports
            ]  # fmt: skip
            self.ws += [
                Process(
                    "uvicorn" if not hosts else f"uvicorn-{host.name}",
                    [
                        *host.prefix, sys.executable, "-m", "iouv.serve",
                        "--host", host.address, "--port", str(port),
                    ],
                    env_there,
                    port,
                    host=host.address,
                )
                for port in ws_ports
            ]  # fmt: skip
        self.nginx: subprocess.Popen[bytes] | None = None
        self.context = self.certificates.client_context()

    @contextlib.contextmanager
    def running(self) -> Iterator[ProductionShape]:
        """Everything started (static files collected first), stopped on exit."""
        subprocess.run(
            [sys.executable, "manage.py", "collectstatic", "--noinput", "-v", "0"],
            cwd=ROOT,
            env=self.env,
            check=True,
        )
        prefix = self.workdir / "nginx"
        site = nginx_site(
            web=[p.address for p in self.web],
            ws=[p.address for p in self.ws],
            https=self.https,
            http=self.http,
            certificates=self.certificates,
            static_root=self.workdir / "static",
            server_options=self.server_options,
            upstream_keepalive=self.upstream_keepalive,
        )
        nginx_prepared(prefix, site)
        try:
            for process in [*self.web, *self.ws]:
                process.start()
            with open(prefix / "error.log", "a") as log:
                self.nginx = subprocess.Popen(
                    nginx_command(prefix), stdout=log, stderr=subprocess.STDOUT
                )
            _wait_http(f"{self.base}/healthz", context=self.context)
            if not self.with_worker:
                yield self
                return
            with celery_worker_process(extra_env=self.env) as worker:
                self.worker = worker
                yield self
        finally:
            if self.nginx is not None and self.nginx.poll() is None:
                self.nginx.send_signal(signal.SIGQUIT)
                try:
                    self.nginx.wait(10)
                except subprocess.TimeoutExpired:
                    self.nginx.kill()
            for process in [*self.ws, *self.web]:
                process.stop()


JANUS = DEPLOY / "janus"


def janus_rendered(
    *,
    configs: Path,
    libdir: Path,
    http_port: int,
    ws_port: int,
    token_secret: str,
    admin_key: str,
    rtp_ports: str | None,
) -> dict[str, str]:
    """``deploy/janus``'s configuration files as ``deploy/janus/render`` writes them,
    with the test's folders, ports and secrets: file name -> text."""
    values = {
        "@CONFIGS@": str(configs),
        "@LIBDIR@": str(libdir),
        "@HTTP_PORT@": str(http_port),
        "@WS_PORT@": str(ws_port),
        "@RTP_PORT_RANGE@": f'rtp_port_range = "{rtp_ports}"' if rtp_ports else "",
        "@IOUV_JANUS_TOKEN_SECRET@": token_secret,
        "@IOUV_JANUS_ADMIN_KEY@": admin_key,
    }
    rendered = {}
    for template in sorted(JANUS.glob("*.jcfg")):
        text = template.read_text()
        for placeholder, value in values.items():
            text = text.replace(placeholder, value)
        rendered[template.name] = text
    return rendered
