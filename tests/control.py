"""The browser's side of the control protocol, for tests that talk to an agent's
control socket (directly or through the platform's relay) as a controller page does."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

from websockets.asyncio.client import ClientConnection


async def recv(ws: ClientConnection, kind: str, within: float = 3.0) -> dict[str, Any]:
    """The next message of type ``kind`` (answering pings, skipping telemetry and
    events); raises TimeoutError after ``within`` seconds."""
    deadline = time.monotonic() + within
    while True:
        # asyncio.timeout, not wait_for: 3.11's wait_for can swallow the cancel of a
        # client stopping its driver, which then drives on forever.
        async with asyncio.timeout(max(0.0, deadline - time.monotonic())):
            raw = await ws.recv()
        msg = json.loads(raw)
        if msg["type"] == kind:
            return msg
        if msg["type"] == "ping":
            await ws.send(json.dumps({"type": "pong", "t": msg["t"]}))


async def command(ws: ClientConnection, seq: int, name: str, **args: Any) -> dict[str, Any]:
    """Send command ``name`` with ``args`` as number ``seq``; returns its ``ack``."""
    await ws.send(json.dumps({"type": "command", "seq": seq, "name": name, "args": args}))
    return await recv(ws, "ack")


async def event_named(ws: ClientConnection, name: str, within: float = 3.0) -> dict[str, Any]:
    """The next ``event`` named ``name``, past the others (a ``consequence`` the agent
    sends as what ending the session would do changes); TimeoutError after ``within``."""
    deadline = time.monotonic() + within
    while True:
        event = await recv(ws, "event", within=max(0.0, deadline - time.monotonic()))
        if event["event"] == name:
            return event
