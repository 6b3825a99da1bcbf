"""The agent's check of the autopilot's GCS fail-safe (agents/vehicles/mavlink/failsafe.py)
against a task, value by value, as ArduPilot reads them: ArduCopter's
``Copter::failsafe_gcs_on_event`` and ``do_failsafe_action`` (ArduCopter/events.cpp),
ArduRover's ``Rover::failsafe_trigger`` (Rover/failsafe.cpp).

The autopilot is a table of parameters behind the link's ``read_param``: a name it lacks
goes unanswered, as ArduPilot leaves it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, cast

import pytest

from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.classes import BOAT, COPTER, VehicleClass
from agents.vehicles.mavlink.failsafe import failsafe_problems
from agents.vehicles.mavlink.link import AutopilotLink

AGENT = 255


@dataclass
class _Config:
    source_system: int = AGENT
    resend_s: float = 0.01
    command_timeout_s: float = 1.0


@dataclass
class ParamTable:
    """An autopilot answering PARAM_REQUEST_READ from ``params``; a name it lacks is
    never answered (AdapterError ``timeout``, at once: nothing here waits)."""

    params: dict[str, float]
    ok: bool = True
    config: _Config = field(default_factory=_Config)

    async def read_param(self, name: str) -> float:
        if name not in self.params:
            raise AdapterError(
                f"the autopilot did not answer for parameter {name} within 1 s", code="timeout"
            )
        return float(self.params[name])


async def problems_of(
    params: dict[str, float], expected: str, vehicle: VehicleClass = COPTER, **kw: Any
) -> list[str]:
    """The check's problems for an autopilot with ``params`` (its GCS id the agent's)."""
    timeout = {"FS_GCS_TIMEOUT": 5.0} if vehicle is COPTER else {"FS_TIMEOUT": 1.5}
    table = {"SYSID_MYGCS": AGENT, **timeout, **params}
    link = cast(AutopilotLink, ParamTable(table))
    problems, found = await failsafe_problems(link, vehicle, expected, **kw)
    assert found == "SYSID_MYGCS"
    return problems


# --- ArduCopter ------------------------------------------------------------------------

#: FS_GCS_ENABLE -> the task actions it agrees with: failsafe_gcs_on_event's action for
#: it (1 and 2 RTL, 3 SmartRTL or RTL, 4 SmartRTL or LAND, 5 LAND, 6 DO_LAND_START or
#: RTL, 7 BRAKE or LAND, anything else the switch's default, RTL).
COPTER_AGREES = {
    1: {"return_to_home"},
    2: {"return_to_home"},
    3: {"return_to_home"},
    4: {"return_to_home"},
    5: {"land"},
    6: {"return_to_home"},
    7: {"stop"},
    8: {"return_to_home"},
    42: {"return_to_home"},
}


@pytest.mark.parametrize("expected", ["return_to_home", "land", "stop"])
@pytest.mark.parametrize("code", sorted(COPTER_AGREES))
async def test_each_fs_gcs_enable_agrees_with_what_arducopter_does_for_it(
    code: int, expected: str
) -> None:
    problems = await problems_of({"FS_GCS_ENABLE": code, "FS_OPTIONS": 16}, expected)
    if expected in COPTER_AGREES[code]:
        assert problems == []
    else:
        [problem] = problems
        assert f"(FS_GCS_ENABLE={code}) but the task expects {expected}" in problem


async def test_the_words_say_what_arducopter_does() -> None:
    [two] = await problems_of({"FS_GCS_ENABLE": 2}, "land")
    assert two.startswith("the autopilot's GCS fail-safe does RTL (else LAND; 2 no longer")
    assert "FS_OPTIONS bit 1 does" in two
    [six] = await problems_of({"FS_GCS_ENABLE": 6}, "stop")
    assert "DO_LAND_START or DO_RETURN_PATH_START in AUTO (else RTL, else LAND)" in six
    [seven] = await problems_of({"FS_GCS_ENABLE": 7}, "return_to_home")
    assert "does BRAKE (else LAND) (FS_GCS_ENABLE=7)" in seven
    [other] = await problems_of({"FS_GCS_ENABLE": 42}, "land")
    assert "does RTL (else LAND: FS_GCS_ENABLE=42 is no value of its own)" in other


async def test_a_disabled_gcs_failsafe_agrees_with_nothing() -> None:
    for expected in ("return_to_home", "land", "stop"):
        [problem] = await problems_of({"FS_GCS_ENABLE": 0}, expected)
        assert "GCS fail-safe is disabled (FS_GCS_ENABLE=0)" in problem


@pytest.mark.parametrize("options", [0, 1, 2, 4, 8, 16, 18, 31])
async def test_fs_options_that_only_make_exceptions_are_no_mismatch(options: int) -> None:
    """Bits 1 (a mission in AUTO goes on), 3 (a landing goes on) and 4 (a pilot's mode
    goes on) never reach GUIDED, where the agent flies; bits 0 and 2 are the radio's."""
    assert await problems_of({"FS_GCS_ENABLE": 1, "FS_OPTIONS": options}, "return_to_home") == []


@pytest.mark.parametrize("options", [32, 34, 48])
async def test_fs_options_bit_5_drops_the_payload_and_is_reported(options: int) -> None:
    [problem] = await problems_of({"FS_GCS_ENABLE": 1, "FS_OPTIONS": options}, "return_to_home")
    assert problem == (
        f"the autopilot's GCS fail-safe also releases the gripper (FS_OPTIONS={options}, "
        "bit 5): a payload on board drops wherever the agent goes silent"
    )


async def test_an_arducopter_without_fs_options_is_judged_by_fs_gcs_enable_alone() -> None:
    """ArduCopter before 4.0 has no FS_OPTIONS: its silence is no problem."""
    assert await problems_of({"FS_GCS_ENABLE": 1}, "return_to_home") == []
    [problem] = await problems_of({"FS_GCS_ENABLE": 5}, "stop")
    assert "does LAND (FS_GCS_ENABLE=5)" in problem


# --- ArduRover -------------------------------------------------------------------------

#: FS_ACTION -> the task actions it agrees with (Rover::failsafe_trigger): 0 nothing,
#: 1 RTL (else Hold), 2 Hold, 3 SmartRTL (else RTL, else Hold), 4 SmartRTL (else Hold),
#: 5 Terminate (disarm), 6 Loiter (else Hold); a boat cannot land, so holding agrees
#: with land too.
ROVER_AGREES: dict[int, set[str]] = {
    0: set(),
    1: {"return_to_home"},
    2: {"land", "stop"},
    3: {"return_to_home"},
    4: {"return_to_home"},
    5: set(),
    6: {"land", "stop"},
}


@pytest.mark.parametrize("enable", [1, 2])
@pytest.mark.parametrize("expected", ["return_to_home", "land", "stop"])
@pytest.mark.parametrize("action", sorted(ROVER_AGREES))
async def test_each_fs_action_agrees_with_what_ardurover_does_for_it(
    action: int, expected: str, enable: int
) -> None:
    """FS_GCS_ENABLE 2 acts as 1 outside AUTO: FS_ACTION decides."""
    params = {"FS_GCS_ENABLE": enable, "FS_ACTION": action}
    problems = await problems_of(params, expected, BOAT)
    if expected in ROVER_AGREES[action]:
        assert problems == []
    else:
        [problem] = problems
        assert f"(FS_ACTION={action}) but the task expects {expected}" in problem


async def test_a_boats_disabled_gcs_failsafe_agrees_with_nothing() -> None:
    [problem] = await problems_of({"FS_GCS_ENABLE": 0, "FS_ACTION": 1}, "return_to_home", BOAT)
    assert "disabled (FS_GCS_ENABLE=0)" in problem and "the boat keeps its last command" in problem
