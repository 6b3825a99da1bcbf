"""Where a long test waits: past ``IOUV_TEST_DUMP_AFTER_S`` (default 300 s, half of
pytest-timeout's limit) a test's stacks are written to its captured stderr, which the
report shows when pytest-timeout then fails it.

pytest-timeout prints the threads' stacks only; for an async test that is the event
loop idle in ``select``, which says nothing. This prints every task of every running
event loop as well, from inside its loop (``call_soon_threadsafe``), so an ``await``
without a bound is named with its line.
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

import pytest


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


def dump_stacks(why: str) -> None:
    """Write every thread's stack and every running loop's tasks to stderr."""
    sys.stderr.write(f"\n===== {why}: threads =====\n")
    faulthandler.dump_traceback(all_threads=True)
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
            sys.stderr.write(f"===== {why}: tasks of {loop!r} =====\n{text.getvalue()}")
        else:
            sys.stderr.write(f"===== {why}: {loop!r} is blocked (see its thread) =====\n")
    sys.stderr.flush()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
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
