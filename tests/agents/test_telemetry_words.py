"""Telemetry topics in words: generic ones described once, an integration's own first."""

from __future__ import annotations

import pytest

from agents.telemetry import GENERIC_TOPICS, TopicInfo, topics_info
from agents.vehicles.base import Adapter
from agents.vehicles.car.adapter import CarAdapter
from agents.vehicles.car.vocabulary import TELEMETRY_TOPICS as CAR_TOPICS
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.mavlink.vocabulary import ROVER_TELEMETRY_TOPICS, TELEMETRY_TOPICS
from agents.vehicles.spektrum.adapter import SpektrumAdapter
from agents.vehicles.spektrum.vocabulary import TELEMETRY_TOPICS as VTOL_TOPICS


def test_an_integrations_own_words_come_before_the_generic_ones_then_the_name() -> None:
    info = topics_info(
        ["altitude", "ekf_ok", "frame_period_ms"],
        {"ekf_ok": TopicInfo("Position estimate", yes="healthy", no="not healthy")},
    )
    assert info == {
        "altitude": {"label": "Altitude", "unit": "m", "decimals": 1},
        "ekf_ok": {"label": "Position estimate", "yes": "healthy", "no": "not healthy"},
        "frame_period_ms": {"label": "Frame period ms"},
    }


@pytest.mark.parametrize(
    "adapter, topics",
    [
        (CarAdapter, CAR_TOPICS),
        (MavlinkAdapter, TELEMETRY_TOPICS + ROVER_TELEMETRY_TOPICS),
        (SpektrumAdapter, VTOL_TOPICS),
    ],
)
def test_every_topic_of_every_integration_has_words_of_its_own(
    adapter: type[Adapter], topics: list[str]
) -> None:
    # No topic falls back to its raw name ("Ekf ok", "Channels throttle 1706").
    own = adapter.telemetry_labels
    missing = [t for t in topics if t not in own and t not in GENERIC_TOPICS]
    assert not missing, f"{adapter.name}: topics without words: {missing}"
