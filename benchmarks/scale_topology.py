"""The platform's process topologies the scale benchmark runs, both behind the shipped
nginx site (``deploy/nginx/iouv.conf``, TLS, routing by path, per-address limits):

* ``single``: one ``python -m iouv.serve`` process (uvicorn, or daphne with
  ``--server``) serving everything, pages, API and WebSockets: both of the site's
  upstreams name it;
* ``production``: the shape ``deploy/`` ships (docs/operations.md, "Production
  layout"): gunicorn HTTP processes (``iouv-web@``), uvicorn WebSocket processes
  (``iouv-ws@``), started from the units' own ``ExecStart`` lines and
  ``deploy/gunicorn.conf.py``; nginx routes ``/ws/`` to the uvicorn processes and the
  rest to gunicorn's.

Both run the Celery worker and beat of ``iouv-worker.service`` and
``iouv-beat.service`` (the supervisor's timers are the platform's work in either), on
the same PostgreSQL and Redis. :func:`nginx_site` is also what tests/production.py runs
the shipped site with.

Clients reach nginx over TLS (a CA of the run's own, trusted through ``SSL_CERT_FILE``
by every client process) from addresses of their own in 127.0.0.0/8
(:func:`loopback_address`): nginx limits connections and requests per address, as it
would for a fleet and its users.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shlex
import shutil
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from benchmarks.nginx_proxy import Backend, NginxProxy, Routes, Tls, worker_connections
from benchmarks.scale_platform import (
    ROOT,
    Child,
    PlatformTree,
    free_port,
    platform_start,
    process_start,
)

TOPOLOGIES = ("single", "production")
DEPLOY = ROOT / "deploy"
SITE = DEPLOY / "nginx" / "iouv.conf"
UNITS = DEPLOY / "systemd"

#: First octet after 127 of each kind of client's addresses (:func:`loopback_address`).
AGENTS_NET, API_NET, FLOOD_NET = 20, 30, 40


def loopback_address(net: int, index: int) -> str:
    """The ``index``-th address of a group of loopback addresses (``127.<net + k>.y.z``,
    y and z in 1..250): a client of its own as nginx's per-address limits see it."""
    per_net = 250 * 250
    k, rest = divmod(index, per_net)
    return f"127.{net + k}.{rest // 250 + 1}.{rest % 250 + 1}"


# --------------------------------------------------------------------------------------
# deploy/'s files, rendered for a run on this machine
# --------------------------------------------------------------------------------------


def nginx_site(
    *,
    web: Sequence[int | str],
    ws: Sequence[int | str],
    https: int,
    http: int,
    certificate: Path,
    key: Path,
    static_root: Path,
    server_options: str = "max_fails=0",
    upstream_keepalive: bool = True,
    site: Path = SITE,
) -> str:
    """``site`` (the shipped ``deploy/nginx/iouv.conf``) listening on loopback ports
    ``https`` and ``http``, proxying to the HTTP processes ``web`` and the WebSocket
    ones ``ws`` (each a port on 127.0.0.1, or ``"host:port"``), with ``certificate``
    (the chain), ``key`` and ``static_root``; ``server_options`` end each upstream
    server's line. Raises AssertionError if the file no longer has a line this replaces
    (the run would not be what production runs). ``upstream_keepalive`` False drops
    the HTTP upstream's idle connections to the processes (``keepalive``)."""
    text = site.read_text()

    def upstream(name: str, servers_at: Sequence[int | str]) -> None:
        nonlocal text
        block = re.compile(rf"(upstream {name} \{{\n)((?:    server [^\n]+\n)+)")
        assert block.search(text), f"no upstream {name} in {site}"
        addresses = [f"127.0.0.1:{at}" if isinstance(at, int) else at for at in servers_at]
        servers = "".join(f"    server {address} {server_options};\n" for address in addresses)
        text = block.sub(lambda m: m.group(1) + servers, text, count=1)

    def replace(old: str, new: str) -> None:
        nonlocal text
        assert old in text, f"{old!r} is not in {site}"
        text = text.replace(old, new)

    upstream("iouv_web", web)
    if not upstream_keepalive:
        replace("    keepalive 32;\n", "")
    upstream("iouv_ws", ws)
    replace("    listen [::]:80;\n", "")
    replace("    listen [::]:443 ssl;\n", "")
    replace("    listen 80;", f"    listen 127.0.0.1:{http};")
    replace("    listen 443 ssl;", f"    listen 127.0.0.1:{https} ssl;")
    replace(
        "return 301 https://$host$request_uri;", f"return 301 https://$host:{https}$request_uri;"
    )
    replace("/etc/ssl/iouv/fullchain.pem", str(certificate))
    replace("/etc/ssl/iouv/privkey.pem", str(key))
    replace("alias /srv/iouv/static/;", f"alias {static_root}/;")
    return text


def nginx_main(prefix: Path, site: str, *, connections: int | None = None) -> str:
    """A main nginx.conf around ``site`` keeping every nginx write under ``prefix``: in
    the foreground, one process (its pid is the one measured), ``connections`` sized for
    the open-file limit (a proxied WebSocket takes two) unless given."""
    temp = prefix / "temp"
    return "\n".join(
        [
            "daemon off;",
            "master_process off;",
            "worker_processes 1;",
            f"pid {prefix / 'nginx.pid'};",
            "error_log stderr notice;",
            f"events {{ worker_connections {connections or worker_connections()}; }}",
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


def unit_command(
    unit: Path, *, root: Path, instance: str = "", state: Path
) -> tuple[list[str], dict[str, str]]:
    """The command line and the ``Environment=`` variables of a systemd unit of
    ``deploy/systemd``, for this machine: ``/opt/iouv/.venv/bin/`` is this
    interpreter's folder, ``/opt/iouv`` is ``root``, ``%i`` is ``instance``, and
    ``/var/lib/iouv`` and ``/run`` are folders under ``state``. Raises ValueError if the
    unit has no ``ExecStart``."""
    text = unit.read_text()
    venv_bin = f"{Path(sys.executable).parent}/"

    def local(value: str) -> str:
        value = value.replace("/opt/iouv/.venv/bin/", venv_bin).replace("/opt/iouv", str(root))
        value = value.replace("/var/lib/iouv", str(state / "lib"))
        value = re.sub(r"(?<![\w/])/run/", f"{state}/run/", value)
        return value.replace("%i", instance)

    command: list[str] = []
    env: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition("=")
        if key == "ExecStart" and value:
            command = shlex.split(local(value))
        elif key == "Environment":
            name, _, setting = local(value).partition("=")
            env[name] = setting
    if not command:
        raise ValueError(f"{unit} has no ExecStart")
    # What systemd would provide: the state directory, the runtime directories (empty
    # at each start, as RuntimeDirectory= makes them).
    (state / "lib").mkdir(parents=True, exist_ok=True)
    for value in env.values():
        if value.startswith(f"{state}/run/"):
            shutil.rmtree(value, ignore_errors=True)
            Path(value).mkdir(parents=True)
    return command, env


# --------------------------------------------------------------------------------------
# Running a topology
# --------------------------------------------------------------------------------------


def descendants(pid: int) -> list[int]:
    """``pid`` and every process below it (a gunicorn master's workers), now."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError, ValueError, IndexError):
            with open(f"/proc/{entry}/stat") as f:
                data = f.read()
            ppid = int(data[data.rindex(")") + 2 :].split()[1])
            children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        current = todo.pop()
        out.append(current)
        todo += children.get(current, [])
    return sorted(out)


def these(*pids: int) -> Callable[[], list[int]]:
    """A role's pids when they never change."""
    return lambda: list(pids)


class SiteProxy(NginxProxy):
    """nginx serving a rendered site (:func:`nginx_site`) instead of a routing table:
    :class:`NginxProxy`'s start, readiness and stop, with the shipped configuration.
    ``port`` is the site's https port, ``redirect_port`` its plain-http one."""

    def __init__(self, site: str, *, https: int, http: int, tls: Tls, prefix: Path, log: Path):
        super().__init__(
            Routes(default=Backend("127.0.0.1", 1)),  # never written: the site routes
            port=https,
            prefix=prefix,
            log=log,
            tls=tls,
            redirect_port=http,
        )
        self.site = site

    def write_config(self) -> Path:
        (self.prefix / "temp").mkdir(parents=True, exist_ok=True)
        path = self.prefix / "nginx.conf"
        path.write_text(nginx_main(self.prefix, self.site))
        return path


@dataclass
class Platform:
    """A topology once started: where clients reach it and what runs it.

    ``roles`` maps a label to a function giving the role's pids now (a gunicorn
    master's workers come and go): the report sums CPU per role. Labels of the
    processes that serve requests start with ``platform``."""

    topology: str
    base: str  # https://127.0.0.1:PORT
    proxy: SiteProxy
    children: list[Child]
    roles: dict[str, Callable[[], list[int]]] = field(default_factory=dict)
    web: list[Child] = field(default_factory=list)
    ws: list[Child] = field(default_factory=list)

    @property
    def ws_url(self) -> str:
        return "wss" + self.base.removeprefix("https")

    async def stop(self) -> None:
        """nginx first, then every process (SIGTERM, then SIGKILL)."""
        await self.proxy.stop()
        for child in reversed(self.children):
            await child.stop()


@dataclass(frozen=True)
class Shape:
    """What to start: the topology, the single process's server, and the production
    shape's sizes (``web`` gunicorn instances of ``web_workers`` workers with
    ``web_threads`` threads each; ``ws`` uvicorn processes)."""

    topology: str = "single"
    server: str = "uvicorn"
    web: int = 1
    web_workers: int = 2
    web_threads: int = 4
    ws: int = 2
    celery: bool = True

    def __post_init__(self) -> None:
        if self.topology not in TOPOLOGIES:
            raise ValueError(f"topology must be one of {TOPOLOGIES}, not {self.topology!r}")
        if self.topology == "production" and self.server != "uvicorn":
            raise ValueError("the production shape serves WebSockets with uvicorn only")

    def describe(self) -> str:
        """How the report names it."""
        if self.topology == "single":
            return f"single: one {self.server} process serving everything, behind nginx"
        return (
            f"production: {self.web} gunicorn instance(s) x {self.web_workers} workers x "
            f"{self.web_threads} threads (HTTP), {self.ws} uvicorn process(es) (WebSockets), "
            "behind nginx"
        )


async def _logged(path: Path, text: str, *, within: float) -> None:
    """Wait until ``text`` is in the log at ``path``; raises RuntimeError (with its
    tail) after ``within`` seconds."""
    deadline = asyncio.get_running_loop().time() + within
    while True:
        logged = await asyncio.to_thread(path.read_text, errors="replace")
        if text in logged:
            return
        if asyncio.get_running_loop().time() > deadline:
            raise RuntimeError(f"{path.name} did not log {text!r}: {logged[-2000:]}")
        await asyncio.sleep(0.2)


async def _site_proxy(
    *, web: list[int], ws: list[int], workdir: Path, tag: str, https: int, http: int
) -> SiteProxy:
    from tests.tls import certificates_make  # the project's own CA maker (cryptography)

    # One CA for the whole run: the clients trust it from their first connection on.
    if not ca_file(workdir).exists():
        certificates_make(workdir / "tls")
    chain, key = workdir / "tls" / "fullchain.pem", workdir / "tls" / "privkey.pem"
    site = nginx_site(
        web=web,
        ws=ws,
        https=https,
        http=http,
        certificate=chain,
        key=key,
        static_root=workdir / "static",
    )
    proxy = SiteProxy(
        site,
        https=https,
        http=http,
        tls=Tls(chain, key),
        prefix=workdir / f"nginx-{tag}",
        log=workdir / f"proxy-{tag}.log",
    )
    await proxy.start()
    return proxy


def ca_file(workdir: Path) -> Path:
    """The run's CA certificate, for ``SSL_CERT_FILE`` of every client."""
    return workdir / "tls" / "ca.pem"


def platform_env(env: dict[str, str], workdir: Path) -> dict[str, str]:
    """The environment every platform process of either topology gets: what
    ``/etc/iouv/iouv.env`` holds in production (docs/operations.md) on top of ``env``."""
    (workdir / "static").mkdir(parents=True, exist_ok=True)
    return {
        **env,
        "BEHIND_PROXY": "1",
        "SERVE_STATIC": "0",
        "STATIC_ROOT": str(workdir / "static"),
        "ALLOWED_HOSTS": "127.0.0.1,localhost",
    }


async def topology_start(
    shape: Shape,
    *,
    tree: PlatformTree,
    env: dict[str, str],
    logs: Path,
    extra_single: int = 0,
) -> Platform:
    """Start ``shape``'s processes and nginx with the shipped site in front; returns
    once every HTTP or WebSocket process answers ``/healthz`` and nginx accepts.
    ``extra_single``: single processes started beside the first, idle until the caller
    routes to them (phase 4). Whatever started is stopped if a later start fails."""
    env = platform_env(env, logs)
    # A console script (gunicorn, celery) has its own folder first on the module path,
    # not the working directory: the tree's packages must come first all the same.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tree.root), env.get("PYTHONPATH")]))
    https, http = free_port(), free_port()
    children: list[Child] = []
    roles: dict[str, Callable[[], list[int]]] = {}
    try:
        if shape.topology == "single":
            names = ["platform-1", *(f"platform-{2 + i}" for i in range(extra_single))]
            started = await asyncio.gather(
                *(
                    platform_start(name, server=shape.server, tree=tree, env=env, logs=logs)
                    for name in names
                )
            )
            children += started
            web = ws = [started[0].port]
            roles["platform-1"] = these(started[0].pid)
            web_children, ws_children = [started[0]], [started[0]]
        else:
            units = tree.root / "deploy" / "systemd"
            web_env = {
                **env,
                "IOUV_WEB_WORKERS": str(shape.web_workers),
                "IOUV_WEB_THREADS": str(shape.web_threads),
            }
            web_children, ws_children = [], []
            for i in range(shape.web):
                port = free_port()
                command, unit_env = unit_command(
                    units / "iouv-web@.service", root=tree.root, instance=str(port), state=logs
                )
                web_children.append(
                    await process_start(
                        f"gunicorn-{i + 1}",
                        command,
                        env={**web_env, **unit_env},
                        tree=tree,
                        logs=logs,
                        port=port,
                    )
                )
            for i in range(shape.ws):
                port = free_port()
                command, unit_env = unit_command(
                    units / "iouv-ws@.service", root=tree.root, instance=str(port), state=logs
                )
                ws_children.append(
                    await process_start(
                        f"uvicorn-{i + 1}",
                        command,
                        env={**env, **unit_env},
                        tree=tree,
                        logs=logs,
                        port=port,
                    )
                )
            children += web_children + ws_children
            web, ws = [c.port for c in web_children], [c.port for c in ws_children]
            roles["platform: gunicorn"] = lambda: [
                pid for c in web_children for pid in descendants(c.pid)
            ]
            roles["platform: uvicorn"] = lambda: [c.pid for c in ws_children]
        if shape.celery:
            celery: list[Child] = []
            for name in ("iouv-worker", "iouv-beat"):
                command, unit_env = unit_command(
                    tree.root / "deploy" / "systemd" / f"{name}.service",
                    root=tree.root,
                    state=logs,
                )
                celery.append(
                    await process_start(
                        name, command, env={**env, **unit_env}, tree=tree, logs=logs, port=0
                    )
                )
            children += celery
            # Ready once it says so: its start-up (imports, connecting) is not the
            # platform's idle cost.
            await _logged(logs / "iouv-worker.log", " ready.", within=60)
            roles["celery (worker + beat)"] = lambda: [
                pid for c in celery for pid in descendants(c.pid)
            ]
        proxy = await _site_proxy(web=web, ws=ws, workdir=logs, tag="1", https=https, http=http)
    except BaseException:
        for child in reversed(children):
            await child.stop()
        raise
    assert proxy.process is not None
    roles["nginx (front proxy)"] = these(proxy.process.pid)
    return Platform(
        shape.topology,
        f"https://127.0.0.1:{https}",
        proxy,
        children,
        roles,
        web=web_children,
        ws=ws_children,
    )


async def proxy_reroute(platform: Platform, *, web: list[int], ws: list[int], logs: Path) -> None:
    """Restart nginx on the same ports with the site's upstreams now ``web`` and ``ws``
    (every socket through it is cut, as a restart cuts them)."""
    https, http = platform.proxy.port, platform.proxy.redirect_port
    assert http is not None
    await platform.proxy.stop()
    platform.proxy = await _site_proxy(
        web=web, ws=ws, workdir=logs, tag="2", https=https, http=http
    )
    assert platform.proxy.process is not None
    platform.roles["nginx (front proxy)"] = these(platform.proxy.process.pid)
