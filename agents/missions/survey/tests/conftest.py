"""The survey mission's rig: a quadcopter on its MAVLink simulator with the pieces the
Agent wires together for missions (tests.agents.mission_rig.rigs), its photo camera the
simulated nadir one and its files kept on disk as the agent keeps them
(agents.artifacts), with nobody to upload them to."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from agents.stills import PHOTO_SECTION, NadirSimCamera, StillCamera
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from tests.agents.mission_rig import Rig, rigs

SurveyRigFactory = Callable[..., Awaitable[Rig]]


def photos(rig: Rig) -> list[Path]:
    """The survey's pictures the drone kept, by name."""
    return rig.kept("*/photo-*.jpg")


@pytest.fixture
async def make_survey_rig(tmp_path: Path) -> AsyncIterator[SurveyRigFactory]:
    """``await make_survey_rig(camera=None, **options)``: a drone on its own simulator
    (tests.agents.mission_rig.drone_options) with a 320 x 240 nadir camera of 60°
    (``camera(nadir, drone)``, if given, returns the camera to use instead, built on
    it) and its files kept under ``tmp_path``."""
    async with rigs() as build:
        count = 0

        async def survey_rig(
            camera: Callable[[NadirSimCamera, MavlinkAdapter], StillCamera] | None = None,
            **options: Any,
        ) -> Rig:
            nonlocal count
            count += 1

            def sensors(drone: MavlinkAdapter) -> dict[str, Any]:
                nadir = NadirSimCamera(hfov_deg=60, width=320, height=240, quality=85)
                return {PHOTO_SECTION: nadir if camera is None else camera(nadir, drone)}

            return await build(
                sensors=sensors, artifacts=tmp_path / f"artifacts-{count}", **options
            )

        yield survey_rig
