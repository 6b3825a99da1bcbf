"""An agent's report says when it happened, by the vehicle's clock (``event.at``): a
report queued while the platform was away, or written late by it, keeps its time. The
platform's side: tests/services/test_supervision.py (logged with both times) and
tests/platform/test_database_outage.py (reports sent during an outage)."""

from __future__ import annotations

import json
import time
from unittest import mock

import pytest
import time_machine

from agents.config import AgentConfig
from agents.protocol import ProtocolError, parse_message
from agents.protocol.messages import Event
from agents.runtime import Agent
from tests.agents.car_rig import PUBLIC_PEM, VEHICLE


class _Queue:
    def __init__(self) -> None:
        self.sent: list[Event] = []

    def send(self, message: Event) -> None:
        self.sent.append(message)


def test_a_report_carries_the_time_it_was_made_not_the_time_it_is_sent() -> None:
    config = AgentConfig.from_mapping(
        {
            "platform_url": "ws://127.0.0.1:1",
            "vehicle_id": VEHICLE,
            "credential": "c",
            "platform_public_key": PUBLIC_PEM,
            "adapter": "car",
        }
    )
    agent = Agent(config, adapter=mock.Mock())  # only its reports are looked at
    agent.uplink = _Queue()  # type: ignore[assignment]  # the uplink's outbox
    with time_machine.travel(1_780_000_000.25, tick=False):
        agent.report("speed_limited", "session-1", {"factor": 0.5})
    (report,) = agent.uplink.sent  # type: ignore[attr-defined]
    assert report.at == 1_780_000_000.25
    # On the wire it is the event's "at", and the platform reads it back.
    frame = json.loads(json.dumps({"type": "event", "session_id": "s", "event": "e", "data": {}}))
    assert parse_message(json.dumps({**frame, "at": time.time()}), channel="uplink_to_platform")
    with pytest.raises(ProtocolError) as refused:
        parse_message(json.dumps({**frame, "at": -1}), channel="uplink_to_platform")
    assert refused.value.field == "at"
