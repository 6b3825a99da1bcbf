"""Waiting in tests on a condition rather than for a fixed time."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any


async def until(predicate: Callable[[], Any], *, within: float = 5.0, what: str = "") -> Any:
    """Check ``predicate`` every 10 ms until it returns something true, and return that;
    raises AssertionError (naming ``what``) after ``within`` seconds."""
    deadline = time.monotonic() + within
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what or predicate}")
        await asyncio.sleep(0.01)
    return value
