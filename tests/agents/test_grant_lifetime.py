"""The agent refuses a grant that would be valid longer than it accepts (its
``control.max_grant_lifetime_s``, 900 s by default: three times the platform's grant
lifetime), however well it is signed: a one-year grant used to be accepted, and would
open the vehicle to whoever held it for that year."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from agents.config import MAX_GRANT_LIFETIME_S, AgentConfig, ConfigError
from agents.protocol import ProtocolError, ReplayGuard, UserGrant, load_public_key
from tests.agents.car_rig import PUBLIC_PEM, VEHICLE, Rig, make_grant
from tests.control import recv

YEAR_S = 365 * 24 * 3600.0


def test_a_grant_longer_than_the_bound_is_refused_without_using_its_id() -> None:
    keys, guard = load_public_key(PUBLIC_PEM), ReplayGuard()
    token = make_grant(ttl=YEAR_S)
    with pytest.raises(ProtocolError) as refused:
        UserGrant.verify(token, keys, vehicle_id=VEHICLE, replay_guard=guard, max_lifetime_s=900)
    assert refused.value.code == "lifetime_too_long" and refused.value.field == "exp"
    assert "at most 900 s" in refused.value.message
    assert len(guard) == 0  # refused before its id was remembered
    # The platform's own grants (300 s) pass; so does any grant without a bound given.
    UserGrant.verify(make_grant(ttl=300), keys, vehicle_id=VEHICLE, max_lifetime_s=900)
    UserGrant.verify(token, keys, vehicle_id=VEHICLE)


async def test_the_vehicle_refuses_a_one_year_grant_and_accepts_the_platforms(rig: Rig) -> None:
    assert rig.hub.max_grant_lifetime_s == MAX_GRANT_LIFETIME_S == 900
    ws = await connect(rig.url, proxy=None)
    await ws.send(json.dumps({"type": "auth", "grant": make_grant(ttl=YEAR_S)}))
    error = await recv(ws, "error")
    assert error["code"] == "lifetime_too_long"
    with pytest.raises(ConnectionClosed):
        await asyncio.wait_for(ws.recv(), 3)
    assert ws.close_code == 4401
    assert rig.hub.controller is None
    async with connect(rig.url, proxy=None) as controller:
        await controller.send(json.dumps({"type": "auth", "grant": make_grant(ttl=300)}))
        assert (await recv(controller, "welcome"))["role"] == "controller"


def _config(**control: Any) -> dict[str, Any]:
    return {
        "platform_url": "ws://127.0.0.1:1",
        "vehicle_id": VEHICLE,
        "credential": "c",
        "platform_public_key": PUBLIC_PEM,
        "adapter": "car",
        "control": control,
    }


def test_the_bound_is_the_agent_configs() -> None:
    assert AgentConfig.from_mapping(_config()).control.max_grant_lifetime_s == 900
    config = AgentConfig.from_mapping(_config(max_grant_lifetime_s=1800))
    assert config.control.max_grant_lifetime_s == 1800
    for bad in (0, -5, "900", True):
        with pytest.raises(ConfigError, match=r"control\.max_grant_lifetime_s"):
            AgentConfig.from_mapping(_config(max_grant_lifetime_s=bad))
