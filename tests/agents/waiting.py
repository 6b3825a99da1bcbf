"""Tests that wait and watch: on a condition rather than for a fixed time, and sampling
a value while the test acts, so that its extreme is caught between the test's steps."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import Any, Self


async def until(predicate: Callable[[], Any], *, within: float = 5.0, what: str = "") -> Any:
    """Check ``predicate`` every 10 ms until it returns something true, and return that;
    raises AssertionError (naming ``what``) after ``within`` seconds."""
    deadline = time.monotonic() + within
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what or predicate}")
        await asyncio.sleep(0.01)
    return value


class Sampler:
    """Calls :meth:`sample` every 20 ms from ``async with`` to the end of the block."""

    _task: asyncio.Task[None] | None = None

    def sample(self) -> None:
        raise NotImplementedError

    async def _run(self) -> None:
        while True:
            self.sample()
            await asyncio.sleep(0.02)

    async def __aenter__(self) -> Self:
        self._task = asyncio.create_task(self._run())
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
