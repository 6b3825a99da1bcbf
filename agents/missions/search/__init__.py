"""The ``search`` mission: a rescue drone flies a lawnmower pattern over the sea while
its thermal camera (:mod:`.thermal`, the agent's ``thermal`` section) looks for a person
in the water; see README.md and docs/rescue-agent.md.

The thermal camera, the detector (numpy) and the false-colour video (PyAV) are loaded
only when an agent opens the camera or flies a search.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from agents.missions.registry import Mission, Sensor
from agents.missions.search.spec import SearchSpec

if TYPE_CHECKING:
    from agents.missions.search.runner import SearchRunner
    from agents.missions.search.thermal import ThermalFeed
    from agents.missions.search.video import ThermalVideo


def _runner() -> type[SearchRunner]:
    from agents.missions.search.runner import SearchRunner

    return SearchRunner


def _check(options: Mapping[str, Any]) -> None:
    from agents.missions.search.thermal import thermal_config_check

    thermal_config_check(options)


def _create(options: Mapping[str, Any], pose: Callable[[], Any]) -> ThermalFeed:
    from agents.missions.search.thermal import thermal_feed_create

    return thermal_feed_create(options, pose)


#: The options of the ``video`` section showing the thermal camera (``"source": "thermal"``).
VIDEO_OPTIONS = frozenset({"width", "height", "box_confidence"})


def _video(feed: ThermalFeed, options: Mapping[str, Any]) -> ThermalVideo:
    from agents.missions.search.video import ThermalVideo

    unknown = set(options) - VIDEO_OPTIONS
    if unknown:
        raise ValueError(f"unknown option(s) for thermal video: {', '.join(sorted(unknown))}")
    return ThermalVideo(feed, **options)


MISSION = Mission(
    name="search",
    title="Search the sea for a person with a thermal camera",
    spec=SearchSpec,
    runner=_runner,
    sensor=Sensor(section="thermal", check=_check, create=_create, video=_video),
)
