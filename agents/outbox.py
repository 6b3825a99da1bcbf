"""What the agent's two uploads to the platform share: the flight record's batches
(agents.recording) and the files missions make (agents.artifacts, one unit per chunk).

Each owner keeps its units on disk until the platform acknowledges them; an
:class:`AckedOutbox` decides which of them go now. It sends nothing while the uplink is
down, keeps at most ``in_flight`` units unanswered at a time, and sends a unit again on
every new uplink connection and after ``resend_s`` without an answer. The owner lists
what is still to deliver, oldest first, each time the outbox asks (:data:`Units`), and
says when a unit is acknowledged or gone (:meth:`AckedOutbox.acked`,
:meth:`AckedOutbox.forget`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, Iterable
from typing import Final, Protocol, TypeAlias

from agents.protocol.messages import Message

log = logging.getLogger(__name__)

#: How often the loop looks again without being woken: a new uplink connection and a
#: unit's resend time wake nobody.
POLL_S: Final = 1.0

#: Builds a unit's message when the outbox sends it; None when the unit turned out
#: unreadable (its owner has dropped it and said so in the log).
Build: TypeAlias = Callable[[], Message | None]
#: The units still to deliver, oldest first, as ``(unit id, build)``: called on every
#: pass and read lazily, only as far as there is room in flight.
Units: TypeAlias = Callable[[], Iterable[tuple[str, Build]]]


class UplinkPort(Protocol):
    """The part of :class:`agents.uplink.Uplink` the outbox uses."""

    connected: asyncio.Event
    connections: int

    def send(self, message: Message) -> None: ...


class AckedOutbox:
    """Sends an owner's units over the uplink until each is acknowledged (module
    docstring).

    ``units`` lists what is still to deliver; ``name`` names the loop's task, and
    ``what`` the upload in the log. :attr:`uplink` is set once the uplink exists.
    :meth:`start` and :meth:`stop` run the loop; :meth:`upload` is one pass of it.
    """

    def __init__(
        self,
        units: Units,
        *,
        in_flight: int,
        resend_s: float,
        name: str,
        what: str,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.uplink: UplinkPort | None = None
        self.in_flight = in_flight
        self.resend_s = resend_s
        self.name = name
        self.what = what
        self.clock = clock
        self._units = units
        # unit id -> (the uplink connection it was last sent on, when). Only units still
        # in flight are kept: any other is due, as one never sent is.
        self._sent: dict[str, tuple[int, float]] = {}
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Run the upload loop (in the running event loop) until :meth:`stop`."""
        if self._task is None:
            self._task = asyncio.create_task(self._run(), name=self.name)

    async def stop(self) -> None:
        """End the upload loop; what was not acknowledged stays with the owner."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def wake(self) -> None:
        """Something may be due (a new unit, a slot freed): look now, not at the next
        poll."""
        self._wake.set()

    def acked(self, unit_id: str) -> None:
        """The platform answered ``unit_id``: its slot is free for the next unit."""
        self.forget(unit_id)
        self.wake()

    def forget(self, unit_id: str) -> None:
        """Drop what the outbox knows of ``unit_id`` (its owner dropped or replaced it):
        it holds no slot, and a unit listed again under that id is sent at once."""
        self._sent.pop(unit_id, None)

    async def _run(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(POLL_S):
                    await self._wake.wait()
            self._wake.clear()
            try:
                self.upload()
            except Exception:  # the next pass tries again; the owner's units stay
                log.exception("%s failed", self.what)

    def upload(self) -> None:
        """One pass: send the units that are due, oldest first, while fewer than
        ``in_flight`` are unanswered. Nothing without a connected uplink."""
        uplink = self.uplink
        if uplink is None or not uplink.connected.is_set():
            return
        connection, now = uplink.connections, self.clock()

        def fresh(sent: tuple[int, float]) -> bool:
            return sent[0] == connection and now - sent[1] < self.resend_s

        # A unit sent on an earlier connection or too long ago is due again: forgetting
        # it here keeps the bookkeeping as small as what is in flight.
        self._sent = {unit_id: sent for unit_id, sent in self._sent.items() if fresh(sent)}
        if len(self._sent) >= self.in_flight:
            return
        for unit_id, build in self._units():
            if unit_id in self._sent:
                continue
            message = build()
            if message is None:
                continue
            uplink.send(message)
            self._sent[unit_id] = (connection, now)
            if len(self._sent) >= self.in_flight:
                return
