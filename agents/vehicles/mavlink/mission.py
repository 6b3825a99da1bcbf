"""The MAVLink mission protocol, from the ground station's side, and a flight plan as
ArduPilot mission items.

:func:`items_upload` is the upload every mission type shares (the mission, and the
fence of :mod:`.fence`): MISSION_COUNT, then the item the autopilot asks for with each
MISSION_REQUEST_INT (or MISSION_REQUEST, which ArduPilot sends), then its MISSION_ACK.
Each message is resent until answered (the link's ``resend_s``), within the link's
``command_timeout_s`` per answer. A MISSION_ACK other than ACCEPTED ends the upload as
AdapterError ``autopilot_refused`` naming the result and what the autopilot said with
it, but for MAV_MISSION_INVALID_SEQUENCE: that is the answer to a resent item the
autopilot had already taken (its request for the next one was lost), and it asks for
the next one again by itself.

:func:`items_download` reads the autopilot's mission back (MISSION_REQUEST_LIST, its
MISSION_COUNT, then MISSION_REQUEST_INT for each item and a MISSION_ACK at the end), as
a ground station does when it connects to a vehicle already flying; :func:`items_match`
says whether what it read is what :func:`plan_items` makes of a plan.

:func:`plan_items` turns a plan (:mod:`agents.vehicles.plan`) into ArduPilot's items:
item 0 is home (ArduPilot keeps home there and never flies it), the plan from item 1
(a vehicle that does not fly has no take-off, so the indices of the two differ: the
items come with the plan index of each). Altitudes are relative to home
(MAV_FRAME_GLOBAL_RELATIVE_ALT_INT); a waypoint's hold time is its param 1; a speed is
DO_CHANGE_SPEED (ground speed); the release is the payload's own (DO_GRIPPER release,
or DO_SET_SERVO to its PWM); the return is NAV_RETURN_TO_LAUNCH; a hold is
NAV_LOITER_UNLIM at the last waypoint's position and altitude (none before it: at 0, 0
and 0 m, which ArduPilot reads as where the vehicle is and its current altitude),
radius (param 3) 0, which ArduCopter and ArduRover never verify as done: the mission
stays on it, in AUTO, until the mode changes.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from agents.vehicles.base import AdapterError
from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.link import AutopilotLink
from agents.vehicles.plan import (
    Hold,
    PlanItem,
    Release,
    ReturnHome,
    Speed,
    TakeOff,
    Waypoint,
)

REQUESTS = ("MISSION_REQUEST_INT", "MISSION_REQUEST")
#: What a refusal means, for the words of the AdapterError (ArduPilot explains some in
#: a STATUSTEXT, but after its MISSION_ACK: it may or may not have come yet).
RESULT_HINTS = {
    int(MAV.MAV_MISSION_NO_SPACE): "more items than the autopilot stores",
    int(MAV.MAV_MISSION_DENIED): "another ground station is uploading",
    int(MAV.MAV_MISSION_UNSUPPORTED): "an item the autopilot does not know",
    int(MAV.MAV_MISSION_UNSUPPORTED_FRAME): "an item in a frame the autopilot does not take",
    int(MAV.MAV_MISSION_OPERATION_CANCELLED): "the upload stalled and the autopilot gave up",
    int(MAV.MAV_MISSION_ERROR): "the autopilot could not store it",
}
#: MAV_FRAME_MISSION: a "do" item's frame (it has no position).
FRAME_MISSION = 2


@dataclass(frozen=True)
class MissionItem:
    """One item, as MISSION_ITEM_INT carries it (position in degrees, z in metres)."""

    command: int
    frame: int = FRAME_MISSION
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    lat: float = 0.0
    lon: float = 0.0
    z: float = 0.0


def result_name(result: int | None) -> str:
    """``MAV_MISSION_NO_SPACE`` for its number."""
    entry = MAV.enums["MAV_MISSION_RESULT"].get(result) if result is not None else None
    return entry.name if entry is not None else f"result {result}"


def _ours(link: AutopilotLink, mission_type: int) -> Callable[[Any], bool]:
    """Whether a message of the mission protocol is about ``mission_type`` and for this
    ground station (or for any)."""
    me = link.config.source_system

    def ours(m: Any) -> bool:
        return bool(
            getattr(m, "mission_type", 0) == mission_type
            and getattr(m, "target_system", 0) in (0, me)
        )

    return ours


async def items_upload(
    link: AutopilotLink, mission_type: int, items: Sequence[MissionItem], *, what: str
) -> None:
    """Upload ``items`` as the autopilot's ``mission_type`` (none: MISSION_CLEAR_ALL).
    Raises AdapterError ``autopilot_refused`` (a MISSION_ACK other than ACCEPTED),
    ``timeout`` or ``autopilot_lost``. See the module docstring."""
    target = link.target_or_default()
    started = time.monotonic()
    ours = _ours(link, mission_type)

    def ack(m: Any) -> bool:
        return bool(m.get_type() == "MISSION_ACK" and m.type != MAV.MAV_MISSION_INVALID_SEQUENCE)

    def requested_or_ack(seq: int) -> Callable[[Any], bool]:
        def match(m: Any) -> bool:
            return ours(m) and (ack(m) or (m.get_type() in REQUESTS and int(m.seq) == seq))

        return match

    if not items:
        answer = await link.request(
            lambda: MAV.MAVLink_mission_clear_all_message(target[0], target[1], mission_type),
            "MISSION_ACK",
            lambda m: ours(m) and ack(m),
            what=f"clearing the {what}",
        )
        _check_ack(link, answer, what, started)
        return

    def item(seq: int) -> Any:
        it = items[seq]
        return MAV.MAVLink_mission_item_int_message(
            target[0], target[1], seq, it.frame, it.command, 0, 1, *it.params,
            round(it.lat * 1e7), round(it.lon * 1e7), it.z, mission_type,
        )  # fmt: skip

    count = len(items)
    answer = await link.request(
        lambda: MAV.MAVLink_mission_count_message(target[0], target[1], count, mission_type),
        ("MISSION_ACK", *REQUESTS),
        requested_or_ack(0),
        what=f"uploading the {what}",
    )
    for seq in range(count):
        if answer.get_type() == "MISSION_ACK":
            break  # refused before the end (NO_SPACE, DENIED, UNSUPPORTED...)
        answer = await link.request(
            functools.partial(item, seq),
            ("MISSION_ACK", *REQUESTS),
            requested_or_ack(seq + 1),
            what=f"uploading {what} item {seq}",
        )
    if answer.get_type() != "MISSION_ACK":
        raise AdapterError(f"the autopilot asked for more {what} items than sent", code="timeout")
    _check_ack(link, answer, what, started)


async def items_download(link: AutopilotLink, mission_type: int, *, what: str) -> list[MissionItem]:
    """The autopilot's ``mission_type`` items, home first for the mission. Raises
    AdapterError ``autopilot_refused`` (a MISSION_ACK instead of the list: another
    ground station is uploading), ``timeout`` or ``autopilot_lost``."""
    target = link.target_or_default()
    ours = _ours(link, mission_type)

    started = time.monotonic()
    answer = await link.request(
        lambda: MAV.MAVLink_mission_request_list_message(target[0], target[1], mission_type),
        ("MISSION_COUNT", "MISSION_ACK"),
        ours,
        what=f"reading the {what} back",
    )
    if answer.get_type() == "MISSION_ACK":
        _check_ack(link, answer, what, started)
        raise AdapterError(f"the autopilot sent no {what} to read", code="timeout")

    def request(seq: int) -> Any:
        return MAV.MAVLink_mission_request_int_message(target[0], target[1], seq, mission_type)

    def item_or_ack(seq: int) -> Callable[[Any], bool]:
        def match(m: Any) -> bool:
            return ours(m) and (m.get_type() == "MISSION_ACK" or int(m.seq) == seq)

        return match

    items: list[MissionItem] = []
    for seq in range(int(answer.count)):
        got = await link.request(
            functools.partial(request, seq),
            ("MISSION_ITEM_INT", "MISSION_ACK"),
            item_or_ack(seq),
            what=f"reading {what} item {seq}",
        )
        if got.get_type() == "MISSION_ACK":
            _check_ack(link, got, what, started)
            raise AdapterError(f"the autopilot ended the {what} download early", code="timeout")
        params = (float(got.param1), float(got.param2), float(got.param3), float(got.param4))
        items.append(
            MissionItem(int(got.command), int(got.frame), params, got.x / 1e7, got.y / 1e7,
                        float(got.z))
        )  # fmt: skip
    # The ground station's last word: the autopilot may stop offering the items.
    link.send(
        MAV.MAVLink_mission_ack_message(
            target[0], target[1], MAV.MAV_MISSION_ACCEPTED, mission_type
        )
    )
    return items


def items_match(stored: Sequence[MissionItem], planned: Sequence[MissionItem]) -> bool:
    """Whether the items read back are the ones planned, home aside (item 0: the
    autopilot writes its own home there). Positions to MISSION_ITEM_INT's 1e-7 degree,
    altitudes and parameters to what a float32 keeps."""
    if len(stored) != len(planned):
        return False

    def close(a: float, b: float) -> bool:
        return abs(a - b) <= 1e-3 * max(1.0, abs(a), abs(b))

    return all(
        a.command == b.command
        and a.frame == b.frame
        and all(close(x, y) for x, y in zip(a.params, b.params, strict=True))
        and abs(a.lat - b.lat) < 2e-7
        and abs(a.lon - b.lon) < 2e-7
        and close(a.z, b.z)
        for a, b in zip(stored[1:], planned[1:], strict=True)
    )


def _check_ack(link: AutopilotLink, answer: Any, what: str, since: float) -> None:
    result = getattr(answer, "type", None)
    if result == MAV.MAV_MISSION_ACCEPTED:
        return
    said = [
        text
        for at, severity, text in link.texts
        if at >= since and severity <= MAV.MAV_SEVERITY_WARNING
    ]
    # What the result means, then what the autopilot said if it came in time.
    words = [w for w in [RESULT_HINTS.get(int(result or -1), ""), *said[-2:]] if w]
    reason = f" ({'; '.join(dict.fromkeys(words))})" if words else ""
    raise AdapterError(
        f"the autopilot refused the {what}: {result_name(result)}{reason}",
        code="autopilot_refused",
    )


def plan_items(
    plan: Sequence[PlanItem],
    *,
    home: tuple[float, float] | None,
    payload: Mapping[str, Any] | None,
    flies: bool = True,
) -> tuple[list[MissionItem], list[int]]:
    """``plan`` as ArduPilot's mission items, home first (see the module docstring), and
    for each item after home the index of the plan item it is. A vehicle that does not
    fly gets no take-off (ArduRover would skip it, with a warning). Raises AdapterError
    ``bad_args`` for a release on a vehicle without a payload."""
    relative = MAV.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    lat, lon = home or (0.0, 0.0)
    items = [MissionItem(MAV.MAV_CMD_NAV_WAYPOINT, MAV.MAV_FRAME_GLOBAL, lat=lat, lon=lon)]
    indices: list[int] = []
    last: Waypoint | None = None
    for index, step in enumerate(plan):
        if isinstance(step, TakeOff):
            if not flies:
                continue
            items.append(MissionItem(MAV.MAV_CMD_NAV_TAKEOFF, relative, z=step.altitude_m))
        elif isinstance(step, Waypoint):
            last = step
            items.append(
                MissionItem(
                    MAV.MAV_CMD_NAV_WAYPOINT, relative, (step.hold_s, 0.0, 0.0, 0.0),
                    step.point[0], step.point[1], step.altitude_m if flies else 0.0,
                )
            )  # fmt: skip
        elif isinstance(step, Hold):
            point, alt = (last.point, last.altitude_m) if last is not None else ((0.0, 0.0), 0.0)
            items.append(
                MissionItem(
                    MAV.MAV_CMD_NAV_LOITER_UNLIM, relative, lat=point[0], lon=point[1],
                    z=alt if flies else 0.0,
                )
            )  # fmt: skip
        elif isinstance(step, Speed):
            speed = (1.0, step.speed_mps, -1.0, 0.0)  # ground speed, no throttle change
            items.append(MissionItem(MAV.MAV_CMD_DO_CHANGE_SPEED, params=speed))
        elif isinstance(step, Release):
            items.append(_release(payload))
        elif isinstance(step, ReturnHome):
            items.append(MissionItem(MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH, relative))
        indices.append(index)
    return items, indices


def _release(payload: Mapping[str, Any] | None) -> MissionItem:
    if payload is None:
        raise AdapterError("this vehicle has no payload to release", code="bad_args")
    if payload.get("method") == "servo":
        params = (float(payload["servo"]), float(payload["pwm"]), 0.0, 0.0)
        return MissionItem(MAV.MAV_CMD_DO_SET_SERVO, params=params)
    return MissionItem(MAV.MAV_CMD_DO_GRIPPER, params=(1, MAV.GRIPPER_ACTION_RELEASE, 0, 0))
