"""Does the autopilot's own fail-safe agree with a task? (its GCS fail-safe: what the
autopilot does when the agent's heartbeats stop).

Read with PARAM_REQUEST_READ at task start (:func:`failsafe_problems`), per vehicle class,
and judged as the firmware reads them:

* ArduCopter (4.x, ``ArduCopter/events.cpp``: ``Copter::failsafe_gcs_on_event``, then
  ``do_failsafe_action``): FS_GCS_ENABLE says what it does (:data:`COPTER_FS_GCS_WORDS`),
  FS_GCS_TIMEOUT after how long; RTL_ALT must not climb above the task's ceiling.
  FS_OPTIONS (``Copter::FailsafeOption``) makes exceptions the task does not see: bit 1
  lets a mission the autopilot flies (AUTO) go on, bit 3 a landing, bit 4 (the
  default, 16) a mode the pilot flies; none of them reaches GUIDED, where the agent
  flies, nor is a mismatch (docs/missions.md chooses bit 1 for deliveries). Bit 5 is:
  the gripper lets go wherever the fail-safe acts;
* ArduRover (rovers, boats; ``Rover/failsafe.cpp``: ``Rover::failsafe_trigger``):
  FS_GCS_ENABLE switches it on (2, "continue with mission in Auto", lets a mission in
  AUTO go on, as ArduCopter's FS_OPTIONS bit 1), FS_ACTION says what it does (RTL,
  Hold, SmartRTL...), FS_TIMEOUT after how long;
* both: the GCS system id it listens to, ``MAV_GCS_SYSID`` (with ``MAV_GCS_SYSID_HI``,
  ArduPilot 4.7 and later) or else ``SYSID_MYGCS``, must be the agent's.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping

from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.classes import VehicleClass
from agents.vehicles.mavlink.link import AutopilotLink

logger = logging.getLogger(__name__)

#: FS_GCS_ENABLE -> what ArduCopter 4.x does when the GCS falls silent (its
#: failsafe_gcs_on_event's FailsafeAction, carried out by do_failsafe_action, each
#: set_mode_* helper falling back as written). 2 was "RTL, or continue a mission in
#: AUTO" until 3.6; since 4.0 it is the same case as 1 (the continuing is FS_OPTIONS
#: bit 1's), converted into 1 plus that bit at boot from 4.0 to 4.3 only, and named
#: at every arming since 4.1 ("PreArm: FS_GCS_ENABLE=2 removed, see FS_OPTIONS").
COPTER_FS_GCS_WORDS = {
    0: "disabled",
    1: "RTL (else LAND)",
    2: "RTL (else LAND; 2 no longer continues a mission: FS_OPTIONS bit 1 does)",
    3: "SmartRTL (else RTL, else LAND)",
    4: "SmartRTL (else LAND)",
    5: "LAND",
    6: "the mission's DO_LAND_START or DO_RETURN_PATH_START in AUTO (else RTL, else LAND)",
    7: "BRAKE (else LAND)",
}
#: What any other value does: the switch's default.
COPTER_FS_GCS_DEFAULT = "RTL (else LAND: FS_GCS_ENABLE={code} is no value of its own)"
#: Which of them agree with a task's fail-safe action; any value not named does RTL
#: and agrees with ``return_to_home``.
COPTER_FS_GCS_AGREES = {
    "return_to_home": frozenset({1, 2, 3, 4, 6}),
    "land": frozenset({5}),
    "stop": frozenset({7}),
}
#: FS_OPTIONS bit 5 (Copter::FailsafeOption::RELEASE_GRIPPER): do_failsafe_action
#: releases the gripper after any action.
COPTER_FS_OPTION_RELEASE_GRIPPER = 32
#: FS_ACTION values (ArduRover 4.x, Rover/Parameters.cpp) -> what it does on a fail-safe.
ROVER_FS_ACTION_WORDS = {
    0: "nothing",
    1: "RTL",
    2: "Hold",
    3: "SmartRTL or RTL",
    4: "SmartRTL or Hold",
    5: "Terminate",
    6: "Loiter or Hold",
}
#: Which of them agree with a task's fail-safe action (a rover or boat cannot land: its
#: adapter holds, so a holding fail-safe agrees with "land" too). 4 goes home (SmartRTL
#: retraces the way out) and holds only where SmartRTL cannot start; 5 disarms, which
#: the autopilot cannot undo by itself, so it agrees with nothing.
ROVER_FS_ACTION_AGREES = {
    "return_to_home": frozenset({1, 3, 4}),
    "land": frozenset({2, 6}),
    "stop": frozenset({2, 6}),
}

#: The autopilot parameter naming the GCS its fail-safe follows, newest name first:
#: ArduPilot 4.7 renamed SYSID_MYGCS to MAV_GCS_SYSID (and added MAV_GCS_SYSID_HI, the
#: upper end of a range of GCS ids); an autopilot has one name or the other.
GCS_SYSID_PARAMS = ("MAV_GCS_SYSID", "SYSID_MYGCS")
GCS_SYSID_HI = "MAV_GCS_SYSID_HI"


async def failsafe_problems(
    link: AutopilotLink,
    vehicle_class: VehicleClass,
    expected_action: str,
    *,
    max_altitude_m: float | None = None,
) -> tuple[list[str], str | None]:
    """The mismatches between the autopilot's GCS fail-safe and a task's
    ``expected_action`` (``return_to_home``, ``land`` or ``stop``) in words ([] when
    they agree), and the name the autopilot has for its GCS system id (None when
    neither answered). Never raises: a parameter the autopilot does not answer for is
    itself reported. On an autopilot with the older GCS id name it takes up to
    ``command_timeout_s``: ArduPilot does not answer for a name it lacks."""
    if not link.ok:
        return ["cannot check the autopilot's fail-safe: no link to the autopilot"], None
    copter = vehicle_class.flies
    names = ["FS_GCS_ENABLE", "FS_GCS_TIMEOUT" if copter else "FS_TIMEOUT"]
    if not copter:
        names.append("FS_ACTION")
    if copter and max_altitude_m is not None and expected_action == "return_to_home":
        names.append("RTL_ALT")
    # FS_OPTIONS is read alongside but optional: ArduCopter before 4.0 has none (and
    # then no bit of it can act), so its silence is no problem of its own.
    options_read = asyncio.ensure_future(_read_or_problem(link, "FS_OPTIONS")) if copter else None
    gcs_read = asyncio.ensure_future(_read_gcs_sysid(link))
    answers = await asyncio.gather(*(_read_or_problem(link, name) for name in names))
    values = dict(zip(names, answers, strict=True))
    if options_read is not None:
        values["FS_OPTIONS"] = await options_read
    gcs = await gcs_read
    problems = [value for name in names if isinstance(value := values[name], str)]
    if copter:
        problems += _copter_action(values, expected_action)
    else:
        problems += _rover_action(values, expected_action, vehicle_class.name)
    found: str | None = None
    if isinstance(gcs, str):
        problems.append(gcs)
    else:
        found, low, high = gcs
        agent = link.config.source_system
        if high is not None and high >= low:
            if not low <= agent <= high:
                problems.append(
                    f"the autopilot's GCS fail-safe follows systems {low}-{high} ({found}, "
                    f"{GCS_SYSID_HI}) but the agent is system {agent}: it would never see "
                    "the agent's heartbeats"
                )
        elif low != agent:
            problems.append(
                f"the autopilot's GCS fail-safe follows system {low} ({found}) but the agent "
                f"is system {agent}: it would never see the agent's heartbeats"
            )
    rtl_alt = values.get("RTL_ALT")
    if (
        isinstance(rtl_alt, float)
        and max_altitude_m is not None
        and rtl_alt / 100.0 > max_altitude_m
    ):
        problems.append(
            f"RTL climbs to {rtl_alt / 100.0:g} m (RTL_ALT={rtl_alt:g} cm), above the "
            f"task's {max_altitude_m:g} m ceiling"
        )
    return problems, found


def _copter_action(values: Mapping[str, float | str], expected: str) -> list[str]:
    """FS_GCS_ENABLE against the task (:data:`COPTER_FS_GCS_WORDS`), and FS_OPTIONS bit
    5 whatever the task: a payload on board drops where the agent went silent."""
    enable = values.get("FS_GCS_ENABLE")
    if not isinstance(enable, float):
        return []
    code = int(enable)
    if code == 0:
        return [
            f"the autopilot's GCS fail-safe is disabled (FS_GCS_ENABLE=0) but the task "
            f"expects {expected}: if the agent stops, the drone keeps its last command"
        ]
    problems: list[str] = []
    words = COPTER_FS_GCS_WORDS.get(code, COPTER_FS_GCS_DEFAULT.format(code=code))
    # A value of no action of its own does RTL, the switch's default.
    action = code if code in COPTER_FS_GCS_WORDS else 1
    if action not in COPTER_FS_GCS_AGREES.get(expected, frozenset()):
        problems.append(
            f"the autopilot's GCS fail-safe does {words} (FS_GCS_ENABLE={code}) but "
            f"the task expects {expected}"
        )
    options = values.get("FS_OPTIONS")
    if isinstance(options, float) and int(options) & COPTER_FS_OPTION_RELEASE_GRIPPER:
        problems.append(
            f"the autopilot's GCS fail-safe also releases the gripper (FS_OPTIONS={int(options)}, "
            "bit 5): a payload on board drops wherever the agent goes silent"
        )
    return problems


def _rover_action(values: Mapping[str, float | str], expected: str, vehicle: str) -> list[str]:
    enable, action = values.get("FS_GCS_ENABLE"), values.get("FS_ACTION")
    if not isinstance(enable, float):
        return []
    if int(enable) == 0:
        return [
            f"the autopilot's GCS fail-safe is disabled (FS_GCS_ENABLE=0) but the task "
            f"expects {expected}: if the agent stops, the {vehicle} keeps its last command"
        ]
    if not isinstance(action, float):
        return []
    code = int(action)
    if code not in ROVER_FS_ACTION_AGREES.get(expected, frozenset()):
        words = ROVER_FS_ACTION_WORDS.get(code, f"action {code}")
        return [
            f"the autopilot's fail-safe does {words} (FS_ACTION={code}) but the task "
            f"expects {expected}"
        ]
    return []


async def _read_or_problem(link: AutopilotLink, name: str) -> float | str:
    """One parameter, or why it could not be read (in words)."""
    try:
        return await link.read_param(name)
    except AdapterError as exc:
        return str(exc)


async def _read_gcs_sysid(link: AutopilotLink) -> tuple[str, int, int | None] | str:
    """(the name the autopilot has, its GCS system id, MAV_GCS_SYSID_HI or None), or
    why neither name could be read (in words). Both names are asked for at once, the
    newer first. ArduPilot answers reads in order and has only one of them, so once
    the older name answered the newer one gets one ``resend_s`` more (an autopilot
    with both, or a reordering link), then the older one counts."""
    loop = asyncio.get_running_loop()
    tasks = [asyncio.ensure_future(link.read_param(name)) for name in GCS_SYSID_PARAMS]
    try:
        pending: set[asyncio.Future[float]] = set(tasks)
        grace_until: float | None = None
        while pending:
            wait = None if grace_until is None else max(0.0, grace_until - loop.time())
            done, pending = await asyncio.wait(
                pending, timeout=wait, return_when=asyncio.FIRST_COMPLETED
            )
            if not done:
                break  # the newer name's grace is over
            answered = [t.done() and t.exception() is None for t in tasks]
            if answered[0] or (answered[1] and tasks[0].done()):
                break
            if answered[1] and grace_until is None:
                grace_until = loop.time() + link.config.resend_s
        for name, task in zip(GCS_SYSID_PARAMS, tasks, strict=True):
            if task.done() and task.exception() is None:
                value = int(task.result())
                logger.info("mavlink: the autopilot's GCS system id: %s=%d", name, value)
                high = None
                if name == "MAV_GCS_SYSID":
                    answer = await _read_or_problem(link, GCS_SYSID_HI)
                    high = int(answer) if isinstance(answer, float) else None
                return name, value, high
        errors = [t.exception() for t in tasks if t.done()]
        lost = [e for e in errors if isinstance(e, AdapterError) and e.code != "timeout"]
        if lost:
            return str(lost[0])
        return (
            f"the autopilot did not answer for parameter {' or '.join(GCS_SYSID_PARAMS)} "
            f"within {link.config.command_timeout_s:g} s"
        )
    finally:
        for task in tasks:
            if not task.done():
                task.cancel()
            elif not task.cancelled():
                task.exception()  # retrieved: a failed read is part of the answer
