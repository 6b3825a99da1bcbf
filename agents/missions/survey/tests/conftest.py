"""The survey mission's rig: a quadcopter on its MAVLink simulator with the pieces the
Agent wires together for missions, its photo camera the simulated nadir one and its
files kept on disk as the agent keeps them (agents.artifacts), with nobody to upload
them to."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from agents.artifacts import ArtifactStore
from agents.control import ControlHub
from agents.missions.control import MissionControl
from agents.protocol import load_public_key
from agents.simulation import simulator_running
from agents.stills import PHOTO_SECTION, NadirSimCamera, StillCamera
from agents.vehicles.mavlink.adapter import MavlinkAdapter
from agents.vehicles.registry import adapter_create
from tests.agents.mission_rig import PUBLIC_PEM, VEHICLE, Rig, drone_options


@dataclass
class SurveyRig(Rig):
    store: ArtifactStore | None = None

    def photos(self) -> list[Path]:
        assert self.store is not None
        return sorted(self.store.directory.glob("*/photo-*.jpg"))


SurveyRigFactory = Callable[..., Awaitable[SurveyRig]]


@pytest.fixture
async def make_survey_rig(tmp_path: Path) -> AsyncIterator[SurveyRigFactory]:
    """``await make_survey_rig(camera=None, **options)``: a drone on its own simulator
    (tests.agents.mission_rig.drone_options) with a 320 x 240 nadir camera of 60°
    (``camera(nadir, drone)``, if given, returns the camera to use instead, built on
    it); everything closed at the end, the simulators last."""
    opened: list[SurveyRig] = []
    async with contextlib.AsyncExitStack() as stack:

        async def build(
            camera: Callable[[NadirSimCamera, MavlinkAdapter], StillCamera] | None = None,
            **options: Any,
        ) -> SurveyRig:
            simulation = await stack.enter_async_context(
                simulator_running("mavlink", drone_options(**options))
            )
            drone = adapter_create("mavlink", simulation.options)
            assert isinstance(drone, MavlinkAdapter)
            await drone.start()
            store = await stack.enter_async_context(
                ArtifactStore(directory=tmp_path / f"artifacts-{len(opened)}")
            )
            nadir = NadirSimCamera(hfov_deg=60, width=320, height=240, quality=85)
            photo = nadir if camera is None else camera(nadir, drone)
            reports: list[tuple[str, str | None, dict[str, Any]]] = []
            holder: list[MissionControl] = []
            hub = ControlHub(
                vehicle_id=VEHICLE,
                vehicle_name="surveyor-1",
                public_key=load_public_key(PUBLIC_PEM),
                adapter=drone,
                report=lambda e, s, d: reports.append((e, s, d)),
                on_task_end=lambda task: holder[0].task_ended(task),
            )
            await hub.start()
            missions = MissionControl(
                hub=hub,
                adapter=drone,
                report=lambda e, s, d: reports.append((e, s, d)),
                sensors={PHOTO_SECTION: photo},
                artifacts=store,
            )
            holder.append(missions)
            rig = SurveyRig(drone, hub, missions, None, reports, store=store)  # type: ignore[arg-type]
            opened.append(rig)
            return rig

        try:
            yield build
        finally:
            for rig in reversed(opened):
                await rig.missions.close()
                await rig.hub.close()
                await rig.drone.close()  # idempotent: a test may have killed it
