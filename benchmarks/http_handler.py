"""The platform process's CPU per HTTP request, under its handler and under Django's.

    python -m benchmarks.http_handler [--requests 2000] [--rounds 2]

Starts daphne serving the platform (``iouv.asgi``, whose handler runs a request's
middleware and view in one thread hop, iouv.handler) and then the same settings behind
Django's own ASGI handler (benchmarks.http_django), in turn, ``--rounds`` times each,
on a database it creates, migrates and fills with one user, her API token and one
service (``--database-url``, dropped first). One client sends ``--requests``
``GET /api/v1/services`` one after the other on one kept-alive connection (after 200
to warm up); the process's CPU (user + system, from /proc) and the wall time over them,
per request, are printed as a table. Nothing else runs against the process, so the
difference is the handler's. Nothing is asserted: the table is for comparing.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.scale_platform import database_create, free_port

ROOT = Path(__file__).resolve().parent.parent
APPS = {
    "iouv.handler (one hop)": "iouv.asgi:application",
    "Django's": "benchmarks.http_django:application",
}
PATH = "/api/v1/services"
WARM_UP = 200
CLK_TCK = os.sysconf("SC_CLK_TCK")

# Run by the benchmark in a child process, on the benchmark's database.
_FILL = """
import django
django.setup()
from accounts.roles import CLIENT, roles_ensure, user_set_roles
from accounts.tokens import token_issue
from django.contrib.auth import get_user_model
from services.models import Service, ServiceGrant, ServiceRole
user = get_user_model().objects.create_user(username="bench", password="not-used-here")
user_set_roles(user=user, roles=[CLIENT])
service = Service.objects.create(name="Fly", slug="fly", kind="manual_control")
ServiceRole.objects.create(service=service, name="vehicle")
ServiceGrant.objects.create(service=service, group=roles_ensure()[CLIENT])
print(token_issue(user=user, name="benchmark"))
"""


@dataclass(frozen=True)
class Run:
    handler: str
    cpu_ms: float  # the process's CPU per request
    wall_ms: float  # per request, one at a time


def _env(database_url: str) -> dict[str, str]:
    return {
        **os.environ,
        "DATABASE_URL": database_url,
        "IOUV_DEV_SECRETS": "1",
        "SECURE_SSL_REDIRECT": "0",
        "ALLOWED_HOSTS": "127.0.0.1",
        "DJANGO_SETTINGS_MODULE": "iouv.settings",
        "PYTHONUNBUFFERED": "1",
    }


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def prepare(database_url: str) -> str:
    """A fresh, migrated database with a user, her token (returned) and a service."""
    database_create(database_url, fresh=True)
    env = _env(database_url)
    manage = [sys.executable, str(ROOT / "manage.py")]
    subprocess.run([*manage, "migrate", "-v0"], env=env, cwd=ROOT, check=True)
    filled = subprocess.run(
        [sys.executable, "-c", _FILL], env=env, cwd=ROOT, check=True, capture_output=True, text=True
    )
    return filled.stdout.split()[-1]


def measure(*, handler: str, app: str, token: str, requests: int, database_url: str) -> Run:
    """Start daphne serving ``app``, send the requests, stop it."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "daphne", app, "-b", "127.0.0.1", "-p", str(port)],
        env=_env(database_url),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
                conn.request("GET", "/healthz")
                conn.getresponse().read()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"daphne serving {app} did not start") from None
                time.sleep(0.2)
        headers = {"Authorization": f"Bearer {token}"}

        def one() -> None:
            conn.request("GET", PATH, headers=headers)
            response = conn.getresponse()
            body = response.read()
            if response.status != 200:
                raise RuntimeError(f"{PATH}: {response.status} {body[:200]!r}")

        for _ in range(WARM_UP):
            one()
        cpu, wall = _cpu_s(proc.pid), time.perf_counter()
        for _ in range(requests):
            one()
        cpu, wall = _cpu_s(proc.pid) - cpu, time.perf_counter() - wall
        return Run(handler, 1000 * cpu / requests, 1000 * wall / requests)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def table(runs: list[Run]) -> str:
    lines = [
        "| handler | CPU per request (ms) | wall per request (ms) |",
        "|---|---:|---:|",
    ]
    lines += [f"| {r.handler} | {r.cpu_ms:.2f} | {r.wall_ms:.2f} |" for r in runs]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--requests", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--database-url", default="postgres://postgres@127.0.0.1:5432/iouv_bench_http"
    )
    parser.add_argument("--json", action="store_true", help="print the runs as JSON")
    args = parser.parse_args(argv)
    token = prepare(args.database_url)
    runs = [
        measure(
            handler=handler,
            app=app,
            token=token,
            requests=args.requests,
            database_url=args.database_url,
        )
        for _ in range(args.rounds)
        for handler, app in APPS.items()
    ]
    if args.json:
        print(json.dumps([r.__dict__ for r in runs]))
        return
    print(f"`GET {PATH}`, {args.requests} requests one after the other, {platform.node()}:\n")
    print(table(runs))


if __name__ == "__main__":
    main()
