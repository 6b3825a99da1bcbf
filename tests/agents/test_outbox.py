"""The acknowledged outbox the agent's uploads share (agents.outbox): nothing while the
uplink is down, at most ``in_flight`` units unanswered, again on a new connection and
after ``resend_s``, a slot freed by an ack, an unreadable unit skipped."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

from agents.outbox import AckedOutbox, Build
from agents.protocol.messages import Ack, Message
from tests.agents.waiting import until as wait_until

IN_FLIGHT = 3
RESEND_S = 10.0


class Port:
    """An uplink as the outbox sees it: connected or not, and the ids it was sent."""

    def __init__(self) -> None:
        self.connected = asyncio.Event()
        self.connections = 0
        self.sent: list[str] = []
        #: The next send raises (once), as a broken connection's would.
        self.failing = False

    def connect(self) -> None:
        self.connections += 1
        self.connected.set()

    def send(self, message: Message) -> None:
        assert isinstance(message, Ack)
        if self.failing:
            self.failing = False
            raise ConnectionError("gone")
        self.sent.append(message.id)


class Owner:
    """Units ``u0``, ``u1``... in order, until acknowledged; each sent as an ``ack``
    message carrying its id (any message will do). An id in ``unreadable`` builds
    nothing and is dropped, as an owner drops a file it cannot read."""

    def __init__(self, count: int) -> None:
        self.units = [f"u{i}" for i in range(count)]
        self.unreadable: set[str] = set()
        self.now = 0.0
        self.outbox = AckedOutbox(
            self.listed,
            in_flight=IN_FLIGHT,
            resend_s=RESEND_S,
            name="test-upload",
            what="test upload",
            clock=lambda: self.now,
        )

    def listed(self) -> Iterator[tuple[str, Build]]:
        for unit_id in list(self.units):
            yield unit_id, lambda unit_id=unit_id: self.build(unit_id)

    def build(self, unit_id: str) -> Message | None:
        if unit_id in self.unreadable:
            self.units.remove(unit_id)
            return None
        return Ack(id=unit_id, ok=True)

    def ack(self, unit_id: str) -> None:
        self.units.remove(unit_id)
        self.outbox.acked(unit_id)


def test_nothing_is_sent_without_a_connected_uplink() -> None:
    owner, port = Owner(2), Port()
    owner.outbox.upload()  # no uplink yet
    owner.outbox.uplink = port
    owner.outbox.upload()  # one that is not connected
    assert port.sent == []
    port.connect()
    owner.outbox.upload()
    assert port.sent == ["u0", "u1"]
    port.connected.clear()
    owner.ack("u0")
    owner.now += RESEND_S
    owner.outbox.upload()  # u1 is due again, but the uplink is down
    assert port.sent == ["u0", "u1"]


def test_at_most_in_flight_units_go_and_an_ack_frees_a_slot() -> None:
    owner, port = Owner(5), Port()
    owner.outbox.uplink = port
    port.connect()
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2"]
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2"]  # none answered: no room
    owner.ack("u1")
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2", "u3"]  # the next one, in order
    owner.units.remove("u0")
    owner.outbox.forget("u0")  # dropped by its owner: its slot is free too
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2", "u3", "u4"]


def test_units_go_again_on_a_new_connection_and_after_resend_s() -> None:
    owner, port = Owner(4), Port()
    owner.outbox.uplink = port
    port.connect()
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2"]
    port.sent.clear()
    port.connect()  # the uplink came back: what was in flight is lost with it
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2"]
    port.sent.clear()
    owner.now += RESEND_S - 0.1
    owner.outbox.upload()
    assert port.sent == []  # not yet
    owner.now += 0.1
    owner.outbox.upload()
    assert port.sent == ["u0", "u1", "u2"]  # no answer within resend_s
    port.sent.clear()
    owner.ack("u0")
    owner.outbox.upload()
    assert port.sent == ["u3"]


def test_an_unreadable_unit_takes_no_slot() -> None:
    owner, port = Owner(5), Port()
    owner.unreadable = {"u1", "u2"}
    owner.outbox.uplink = port
    port.connect()
    owner.outbox.upload()
    assert port.sent == ["u0", "u3", "u4"]
    assert owner.units == ["u0", "u3", "u4"]


async def test_the_loop_sends_when_woken_and_goes_on_after_a_failed_pass() -> None:
    owner, port = Owner(2), Port()
    owner.outbox.uplink = port
    port.connect()
    port.failing = True
    owner.outbox.start()
    try:
        owner.outbox.wake()
        await wait_until(lambda: not port.failing, within=5)  # that pass raised
        owner.outbox.wake()
        await wait_until(lambda: port.sent == ["u0", "u1"], within=5)
    finally:
        await owner.outbox.stop()
