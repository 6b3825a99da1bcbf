"""Fixtures shared by the agent's tests. Plain helpers are in the modules beside this
one, named for what they hold (car_rig, mavlink_rig, mission_rig, documents, ...)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from tests.agents import mavlink_rig, mission_rig
from tests.agents.car_rig import Rig, car_rig


@pytest.fixture
async def rig() -> AsyncIterator[Rig]:
    """The simulated car behind a control hub and server, alice's task accepted (see
    :func:`tests.agents.car_rig.car_rig`)."""
    async with car_rig() as built:
        yield built


@pytest.fixture
async def make_quad_rig() -> AsyncIterator[mavlink_rig.RigFactory]:
    """``await make_quad_rig(task=None, **options)``: a quadcopter on its own simulator
    behind a control hub and server (see :func:`tests.agents.mavlink_rig.rigs`); all
    closed at the end of the test."""
    async with mavlink_rig.rigs() as build:
        yield build


@pytest.fixture
async def make_mission_rig() -> AsyncIterator[mission_rig.RigFactory]:
    """``await make_mission_rig(persons=None, *, control=False, **options)``: the rescue
    drone on its own simulator with the pieces the Agent wires together for missions
    (see :func:`tests.agents.mission_rig.rigs`); all closed at the end of the test."""
    async with mission_rig.rigs() as build:
        yield build
