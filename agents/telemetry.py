"""Telemetry topics in words a person reads: a label, a unit and a precision per topic.

The abstraction layer's generic topics (battery level, altitude, position, speed,
heading, ...) are described here once; a vehicle integration adds its own topics
(:attr:`agents.vehicles.base.Adapter.telemetry_labels`). The agent sends the
description with the control socket's ``welcome`` (``telemetry_info``), so the
controller page shows "Altitude 12.3 m" instead of "altitude 12.29871".
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class TopicInfo:
    """How a page shows one telemetry topic.

    ``unit`` follows the number (``"m"``, ``"%"``, ``"°"``); ``decimals`` rounds
    numbers (None: as they come); ``yes``/``no`` name a boolean's two values.
    """

    label: str
    unit: str = ""
    decimals: int | None = None
    yes: str = "yes"
    no: str = "no"

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {"label": self.label}
        if self.unit:
            out["unit"] = self.unit
        if self.decimals is not None:
            out["decimals"] = self.decimals
        if (self.yes, self.no) != ("yes", "no"):
            out["yes"], out["no"] = self.yes, self.no
        return out


#: The generic topics every integration may offer, as the paper's abstraction layer names
#: them.
GENERIC_TOPICS: Mapping[str, TopicInfo] = {
    "battery_level": TopicInfo("Battery", "%", 0),
    "altitude": TopicInfo("Altitude", "m", 1),
    "location": TopicInfo("Position"),
    "speed": TopicInfo("Speed", "m/s", 1),
    "heading": TopicInfo("Heading", "°", 0),
    "is_armed": TopicInfo("Motors", yes="armed", no="disarmed"),
    "flight_mode": TopicInfo("Flight mode"),
    "mode": TopicInfo("Mode"),
    "number_of_gps_satellites": TopicInfo("GPS satellites", decimals=0),
    "gps_fix": TopicInfo("GPS fix", yes="yes", no="no fix yet"),
    "in_air": TopicInfo("In the air"),
}


def _label(name: str) -> str:
    """A topic nobody described, said plainly: ``frame_period_ms`` → "Frame period ms"."""
    return name.replace("_", " ").capitalize()


def topics_info(
    names: Iterable[str], own: Mapping[str, TopicInfo] | None = None
) -> dict[str, dict[str, Any]]:
    """The wire description (``telemetry_info``) of the topics ``names``: the
    integration's ``own`` descriptions first, then the generic ones, else the name."""
    out: dict[str, dict[str, Any]] = {}
    for name in names:
        info = (own or {}).get(name) or GENERIC_TOPICS.get(name) or TopicInfo(_label(name))
        out[name] = info.to_wire()
    return out
