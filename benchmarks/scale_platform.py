"""The platform under test in the scale benchmark: which code tree, which ASGI server,
and the child processes that serve it and query its database.

* :class:`PlatformTree`: the current checkout, or a ``git worktree`` of an older
  commit (``--baseline REF``) run with the same virtualenv;
* :func:`platform_start`: one platform process of a tree under daphne or uvicorn,
  on a free loopback port, ready once ``/healthz`` answers;
* :class:`PlatformQueries`: the tree's own ORM, in a child process running
  :mod:`benchmarks.scale_probe`, for everything the benchmark writes to or reads from
  the platform's database (the driver's models could disagree with an older schema);
* :func:`database_create`: the benchmark's database, created (or dropped and created).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from iouv.serve import command as serve_command
from tests.ports import free_port as free_port  # what the tests import from here

ROOT = Path(__file__).resolve().parents[1]
PROBE = Path(__file__).resolve().with_name("scale_probe.py")
#: ASGI servers the benchmark can run the platform under; the first is the default,
#: production's (iouv.serve).
SERVERS = ("uvicorn", "daphne")
START_TIMEOUT_S = 60.0


def open_log(path: Path) -> Any:
    """A child's output file; the child keeps its own descriptor, ours is closed at once."""
    return open(path, "w")


@dataclass
class Child:
    """A process this run started; :meth:`stop` ends it (SIGTERM, then SIGKILL)."""

    name: str
    proc: asyncio.subprocess.Process
    port: int = 0

    @property
    def pid(self) -> int:
        return self.proc.pid

    async def stop(self, grace_s: float = 10.0) -> None:
        if self.proc.returncode is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            self.proc.terminate()
        try:
            await asyncio.wait_for(self.proc.wait(), grace_s)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                self.proc.kill()
            await self.proc.wait()


# --------------------------------------------------------------------------------------
# Code trees
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlatformTree:
    """The platform's code: ``root`` holds ``iouv/``, ``fleet/``... and ``manage.py``.

    ``label`` names it in the report: ``"current"`` for this checkout (with whatever is
    not committed yet), else the ref it was checked out at.
    """

    root: Path = ROOT
    label: str = "current"
    commit: str = ""
    #: Folders put on the module path after ``root`` (see :data:`SITECUSTOMIZE`).
    extra_path: tuple[Path, ...] = ()

    def env(self, base: dict[str, str]) -> dict[str, str]:
        """``base`` with this tree first on the module path: a ``git worktree`` has no
        install of its own (the virtualenv's editable install is ROOT's)."""
        if self.root == ROOT:
            return dict(base)
        path = [
            *(str(p) for p in (self.root, *self.extra_path)),
            *filter(None, base.get("PYTHONPATH", "").split(os.pathsep)),
        ]
        return {**base, "PYTHONPATH": os.pathsep.join(path)}


#: Put on the module path of another tree's processes. The virtualenv's editable
#: install of ROOT adds an import finder that, after ``sys.path`` has failed, finds a
#: module of ROOT's packages missing from the tree (``fleet.liveness`` in a tree from
#: before it): the older platform would run with pieces of the newer one. ``site``
#: imports this once the ``.pth`` files have installed that finder; it takes it out.
SITECUSTOMIZE = """\
import sys

sys.meta_path[:] = [
    f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable__")
]
sys.path_hooks[:] = [
    h for h in sys.path_hooks if not getattr(h, "__module__", "").startswith("__editable__")
]
sys.path_importer_cache.clear()
"""


def git_commit(ref: str, *, cwd: Path = ROOT) -> str:
    """The full commit id ``ref`` names; raises ValueError if it names none."""
    done = subprocess.run(
        ["git", "rev-parse", "--verify", "--quiet", f"{ref}^{{commit}}"],
        cwd=cwd,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode:
        raise ValueError(f"{ref!r} names no commit of {cwd}")
    return done.stdout.strip()


@contextlib.contextmanager
def worktree(ref: str) -> Iterator[PlatformTree]:
    """A detached ``git worktree`` of ``ref`` in a temporary directory, removed (and
    pruned from the repository's list) on exit. The checkout in ROOT is not touched."""
    commit = git_commit(ref)
    parent = Path(tempfile.mkdtemp(prefix="iouv-baseline-"))
    path = parent / commit[:12]
    site = parent / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    subprocess.run(
        ["git", "worktree", "add", "--detach", "--quiet", str(path), commit],
        cwd=ROOT,
        check=True,
    )
    try:
        yield PlatformTree(path, ref, commit, extra_path=(site,))
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=ROOT, check=False)
        shutil.rmtree(parent, ignore_errors=True)
        subprocess.run(["git", "worktree", "prune"], cwd=ROOT, check=False)


# --------------------------------------------------------------------------------------
# Platform processes
# --------------------------------------------------------------------------------------


def server_command(server: str, *, port: int, tree: PlatformTree | None = None) -> list[str]:
    """The command line serving ``iouv.asgi:application`` under ``server`` on loopback.

    uvicorn as production runs it: ``python -m iouv.serve`` (its options and why are
    that module's). A tree older than that module gets the same options on uvicorn's
    command line, with httptools' own head parsing. daphne as its documented alternative
    runs (docs/operations.md, "Choosing the ASGI server"), without an access log.
    """
    if server == "uvicorn":
        if tree is None or (tree.root / "iouv" / "serve.py").exists():
            return serve_command(port=port)
        return [
            *(sys.executable, "-m", "uvicorn", "iouv.asgi:application"),
            *("--host", "127.0.0.1", "--port", str(port)),
            *("--loop", "uvloop", "--http", "httptools", "--ws", "websockets-sansio"),
            *("--ws-per-message-deflate", "false", "--lifespan", "off"),
            *("--no-access-log", "--no-proxy-headers", "--no-server-header"),
        ]
    if server == "daphne":
        return [
            *(sys.executable, "-m", "daphne", "iouv.asgi:application"),
            *("-b", "127.0.0.1", "-p", str(port)),
        ]
    raise ValueError(f"unknown ASGI server {server!r}; one of {', '.join(SERVERS)}")


def _http_ok(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return bool(response.status == 200)
    except (OSError, urllib.error.URLError):
        return False


async def platform_start(
    name: str, *, server: str, tree: PlatformTree, env: dict[str, str], logs: Path
) -> Child:
    """Start one platform process of ``tree`` under ``server`` on a free loopback port;
    returns once ``/healthz`` answers. Raises RuntimeError (with the log's tail) if it
    does not within START_TIMEOUT_S."""
    port = free_port()
    command = server_command(server, port=port, tree=tree)
    return await process_start(name, command, env=env, tree=tree, logs=logs, port=port)


async def process_start(
    name: str, command: list[str], *, env: dict[str, str], tree: PlatformTree, logs: Path, port: int
) -> Child:
    """Run ``command`` in ``tree`` (its output to ``logs/<name>.log``); with a ``port``,
    return once ``/healthz`` answers there. Raises RuntimeError (with the log's tail)
    if it does not within START_TIMEOUT_S, or if the process exits first."""
    log_path = logs / f"{name}.log"
    with open_log(log_path) as log_file:
        proc = await asyncio.create_subprocess_exec(
            *command,
            cwd=tree.root,
            env=tree.env(env),
            stdout=log_file,
            stderr=asyncio.subprocess.STDOUT,
        )
    child = Child(name, proc, port)
    deadline = time.monotonic() + START_TIMEOUT_S
    try:
        while port and not await asyncio.to_thread(_http_ok, f"http://127.0.0.1:{port}/healthz"):
            if proc.returncode is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{name} did not start: {log_path.read_text()[-2000:]}")
            await asyncio.sleep(0.2)
    except BaseException:
        # Not yet the caller's to stop: a run cancelled (SIGTERM) while its processes
        # start must not leave this one behind.
        await child.stop()
        raise
    return child


# --------------------------------------------------------------------------------------
# The tree's ORM, in a child process
# --------------------------------------------------------------------------------------


class PlatformQueryError(RuntimeError):
    """A request to :mod:`benchmarks.scale_probe` failed; the message is its error."""


class PlatformQueries:
    """The benchmark's database work, done by ``tree``'s own code in a child process
    (:mod:`benchmarks.scale_probe`): an async context manager; :meth:`call` runs one
    operation (``prepare``, ``settings``, ``world_build``, ``fleet_check``,
    ``sessions_check``, ``failsafes_logged``) and returns its result.

    Calls are answered one at a time, in order. The child's CPU is the benchmark's,
    not the platform's: :attr:`pid` lets the report count it with the driver.
    """

    def __init__(self, tree: PlatformTree, *, env: dict[str, str], log: Path) -> None:
        self.tree = tree
        self.env = env
        self.log = log
        self.proc: asyncio.subprocess.Process | None = None
        self._lock = asyncio.Lock()

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    async def __aenter__(self) -> PlatformQueries:
        with open_log(self.log) as log_file:
            # -P: the probe's own folder (this tree's benchmarks/) stays off the path.
            self.proc = await asyncio.create_subprocess_exec(
                *(sys.executable, "-P", str(PROBE)),
                cwd=self.tree.root,
                env=self.tree.env(self.env),
                stdin=asyncio.subprocess.PIPE,
                stdout=asyncio.subprocess.PIPE,
                stderr=log_file,
                limit=1 << 26,  # a world of 5,000 vehicles is one line of a few MB
            )
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self.proc is None:
            return
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        await Child("platform queries", self.proc).stop()

    async def call(self, op: str, **args: Any) -> Any:
        """Run ``op`` with ``args`` in the tree; raises PlatformQueryError with the
        child's error (or its log's tail if it died)."""
        assert self.proc is not None and self.proc.stdin and self.proc.stdout
        async with self._lock:
            self.proc.stdin.write(json.dumps({"op": op, "args": args}).encode() + b"\n")
            await self.proc.stdin.drain()
            line = await self.proc.stdout.readline()
        if not line:
            tail = self.log.read_text(errors="replace")[-2000:]
            raise PlatformQueryError(f"{op}: the probe of {self.tree.label} exited: {tail}")
        reply = json.loads(line)
        if "error" in reply:
            raise PlatformQueryError(f"{op} in {self.tree.label}: {reply['error']}")
        return reply["ok"]


# --------------------------------------------------------------------------------------
# The database
# --------------------------------------------------------------------------------------


def database_create(url: str, *, fresh: bool) -> None:
    """Create the database ``url`` names if missing; with ``fresh``, drop it first
    (whoever is connected is disconnected): a tree's migrations cannot undo a newer
    tree's, so a run of another tree starts from nothing."""
    import psycopg
    from psycopg import sql

    parts = urlsplit(url)
    name = unquote(parts.path.lstrip("/"))
    with psycopg.connect(
        host=parts.hostname or None,
        port=parts.port,
        user=unquote(parts.username or "") or None,
        password=unquote(parts.password or "") or None,
        dbname="postgres",
        autocommit=True,
    ) as conn:
        if fresh:
            conn.execute(
                sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(name))
            )
        exists = conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", (name,)).fetchone()
        if not exists:
            conn.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
