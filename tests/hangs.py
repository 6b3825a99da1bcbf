"""Where a long test waits: past ``IOUV_TEST_DUMP_AFTER_S`` (default 300 s, half of
pytest-timeout's limit) in its set-up, call or teardown, a test's stacks are written to
its captured stderr, which the report shows if the test then ends.

pytest-timeout prints the threads' stacks only; for an async test that is the event
loop idle in ``select``, which says nothing. This prints every task of every running
event loop as well, from inside its loop (``call_soon_threadsafe``), so an ``await``
without a bound is named with its line.

Under pytest-xdist a worker's output reaches nobody: its captured stderr, and the
terminal pytest-timeout's thread method writes to before it ends the worker
(``os._exit``), are the worker's own. So the dump also goes to :data:`HANGS` in the
worker's var folder (conftest.py gives each its own), and the run's summary prints
every such file.
"""

from __future__ import annotations

import asyncio
import faulthandler
import gc
import io
import os
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

import pytest
from django.conf import settings

#: The file, in a process's var folder, that keeps its dumps.
HANGS = "hangs.txt"


def _running_loops() -> list[asyncio.AbstractEventLoop]:
    # Loops are not registered anywhere public; the garbage collector knows them all.
    # type(), not isinstance(): a dead weak proxy raises on isinstance.
    return [
        obj
        for obj in gc.get_objects()
        if issubclass(type(obj), asyncio.AbstractEventLoop) and obj.is_running()
    ]


def _print_tasks(out: io.TextIOBase) -> None:
    for task in asyncio.all_tasks():
        print(f"--- {task!r}", file=out)
        task.print_stack(limit=12, file=out)


def _write_stacks(why: str, out: TextIO) -> None:
    out.write(f"\n===== {why}: threads =====\n")
    out.flush()
    faulthandler.dump_traceback(file=out, all_threads=True)
    for loop in _running_loops():
        done = threading.Event()
        text = io.StringIO()

        def in_loop(text: io.StringIO = text, done: threading.Event = done) -> None:
            try:
                _print_tasks(text)
            finally:
                done.set()

        loop.call_soon_threadsafe(in_loop)
        # A loop blocked by synchronous code never runs the callback; its thread's
        # stack above already says where.
        if done.wait(5):
            out.write(f"===== {why}: tasks of {loop!r} =====\n{text.getvalue()}")
        else:
            out.write(f"===== {why}: {loop!r} is blocked (see its thread) =====\n")
    out.flush()


def dump_stacks(why: str) -> None:
    """Write every thread's stack and every running loop's tasks to this process's
    :data:`HANGS` file, and the same to stderr."""
    kept = Path(settings.VAR_DIR) / HANGS
    kept.parent.mkdir(parents=True, exist_ok=True)
    with open(kept, "a+") as out:
        start = out.tell()
        _write_stacks(why, out)
        out.seek(start)
        sys.stderr.write(out.read())
    sys.stderr.flush()


def _kept_dumps() -> list[Path]:
    """The dump files of this run: the controller's, and each xdist worker's."""
    var = Path(settings.VAR_DIR)
    return [path for path in [var / HANGS, *sorted(var.glob(f"worker-*/{HANGS}"))] if path.exists()]


def pytest_sessionstart(session: pytest.Session) -> None:
    # On the controller, before any worker starts: an earlier run's dumps go.
    if not hasattr(session.config, "workerinput"):
        for path in _kept_dumps():
            path.unlink()


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    for path in _kept_dumps():
        terminalreporter.section(f"stacks of a test that ran long ({path})", sep="=")
        terminalreporter.write(path.read_text())


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    after = float(os.environ.get("IOUV_TEST_DUMP_AFTER_S", "300"))
    timer = threading.Timer(
        after, dump_stacks, args=(f"{item.nodeid} still running after {after:g} s",)
    )
    timer.daemon = True
    timer.start()
    try:
        return (yield)
    finally:
        timer.cancel()
