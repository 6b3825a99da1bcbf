"""The simulated autopilots' GCS fail-safe, value by value, against ArduPilot's source:
ArduCopter's ``Copter::failsafe_gcs_on_event`` and ``do_failsafe_action``
(ArduCopter/events.cpp) and its pre-arm check (AP_Arming_Copter::parameter_checks);
ArduRover's ``Rover::failsafe_trigger`` (Rover/failsafe.cpp).

Each test runs the simulator's :class:`~agents.vehicles.mavlink.sim.autopilot.Autopilot`
in this process on a clock of its own: the GCS's heartbeat is heard, the clock moves
past the silence the firmware allows, and the autopilot acts (no link, no sleeping).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from agents.vehicles.mavlink.dialect import MAV
from agents.vehicles.mavlink.sim.autopilot import Autopilot, SimOptions
from agents.vehicles.mavlink.sim.copter import Copter
from agents.vehicles.mavlink.sim.mission import NAV_LAND, NAV_WAYPOINT, Item
from tests.agents.mavlink_rig import HOME

ALT_HOLD, AUTO, GUIDED, LOITER, LAND, POSHOLD, BRAKE = 2, 3, 4, 5, 9, 16, 17
MANUAL, HOLD, ROVER_AUTO, ROVER_RTL, ROVER_GUIDED = 0, 4, 10, 11, 15
GCS = 255
#: ModeAuto's refusal of AUTO_RTL, as STATUSTEXT carries it: its first 50 characters.
NO_LANDING_SEQUENCE = "Mode change to AUTO RTL failed: No landing sequence found"[:50]


@dataclass
class Clock:
    now: float = 1000.0

    def __call__(self) -> float:
        return self.now


@dataclass(frozen=True)
class Heartbeat:
    """A GCS's HEARTBEAT as the autopilot reads it."""

    type: int = int(MAV.MAV_TYPE_GCS)

    def get_srcSystem(self) -> int:
        return GCS

    def get_srcComponent(self) -> int:
        return 190


def autopilot(vehicle: str = "copter", gps: int = 3, **params: float) -> tuple[Autopilot, Clock]:
    clock = Clock()
    options = SimOptions(
        address="udpin:127.0.0.1:0",
        home=HOME,
        vehicle=vehicle,
        gps_fix=gps,
        params={"FS_GCS_ENABLE": 1, **params},
    )
    return Autopilot(options, clock=clock), clock


def airborne(ap: Autopilot, mode: int, up: float = 20.0) -> None:
    """The vehicle armed and (a copter) flying ``up`` m over a point 30 m north of home,
    in ``mode``; the GCS heard just now."""
    v = ap.vehicle
    v.origin_set = True
    v.armed = True
    v.north, v.up = 30.0, up if isinstance(v, Copter) else 0.0
    if isinstance(v, Copter):
        v.landed = False
    assert v.set_mode(mode) is None, v.modes[mode]
    ap._on_heartbeat(Heartbeat())


def silenced(ap: Autopilot, clock: Clock) -> list[str]:
    """The GCS silent past what the firmware allows: the texts the autopilot says."""
    after = ap.vehicle.gcs_failsafe_after_s()
    assert after is not None
    before = len(ap.vehicle.texts)
    clock.now += after + 0.1
    ap._gcs_failsafe(clock.now)
    return [text for _, text in list(ap.vehicle.texts)[before:]]


def mode_name(ap: Autopilot) -> str:
    return ap.vehicle.modes[ap.vehicle.mode]


# --- ArduCopter: FS_GCS_ENABLE ----------------------------------------------------------

#: FS_GCS_ENABLE -> (the mode it ends in, flying in GUIDED with a GPS fix, and what it
#: says after "GCS Failsafe").
COPTER_ACTIONS: dict[int, tuple[str, list[str]]] = {
    1: ("RTL", []),
    2: ("RTL", []),  # 4.x: the same case as 1; no continuing outside FS_OPTIONS
    3: ("SMART_RTL", []),
    4: ("SMART_RTL", []),
    5: ("LAND", []),
    6: ("RTL", [NO_LANDING_SEQUENCE, "Trying RTL Mode"]),
    7: ("BRAKE", []),
    9: ("RTL", []),  # no value of its own: the switch's default
}


@pytest.mark.parametrize("code", sorted(COPTER_ACTIONS))
def test_each_fs_gcs_enable_does_what_arducopter_does(code: int) -> None:
    ap, clock = autopilot(FS_GCS_ENABLE=code)
    airborne(ap, GUIDED)
    said = silenced(ap, clock)
    mode, texts = COPTER_ACTIONS[code]
    assert said == ["GCS Failsafe", *texts]
    assert mode_name(ap) == mode
    assert ap.gcs_failsafe and not ap.vehicle.payload_released


#: Without a position (no GPS), each action's fall-backs (set_mode_*_or_*): RTL, SmartRTL
#: and BRAKE need one, LAND does not.
COPTER_FALLBACKS: dict[int, list[str]] = {
    1: [],
    3: ["SmartRTL Unavailable, Trying RTL Mode"],
    4: ["SmartRTL Unavailable, Using Land Mode"],
    6: [NO_LANDING_SEQUENCE, "Trying RTL Mode"],
    7: ["Trying Land Mode"],
}


@pytest.mark.parametrize("code", sorted(COPTER_FALLBACKS))
def test_without_a_position_each_action_falls_back_to_land(code: int) -> None:
    # FS_OPTIONS 0: else ALT_HOLD, a mode the pilot flies, would go on.
    ap, clock = autopilot(FS_GCS_ENABLE=code, FS_OPTIONS=0)
    airborne(ap, ALT_HOLD)
    ap.vehicle.gps_fix, ap.vehicle.satellites = 0, 0
    said = silenced(ap, clock)
    assert said == ["GCS Failsafe", *COPTER_FALLBACKS[code]]
    assert mode_name(ap) == "LAND"


def test_fs_gcs_enable_0_never_acts() -> None:
    ap, _ = autopilot(FS_GCS_ENABLE=0)
    assert ap.vehicle.gcs_failsafe_after_s() is None


def test_on_the_ground_it_disarms() -> None:
    ap, clock = autopilot()
    airborne(ap, GUIDED)
    assert isinstance(ap.vehicle, Copter)
    ap.vehicle.landed, ap.vehicle.up = True, 0.0
    assert silenced(ap, clock)[0] == "GCS Failsafe - Disarming"
    assert not ap.vehicle.armed


def test_a_failsafe_land_holds_its_altitude_4_s_before_descending() -> None:
    """set_mode_land_with_pause: LAND_WITH_DELAY_MS (4 s) before the descent."""
    ap, clock = autopilot(FS_GCS_ENABLE=5)
    airborne(ap, GUIDED)
    v = ap.vehicle
    silenced(ap, clock)
    assert mode_name(ap) == "LAND"
    for _ in range(350):  # 3.5 s of flight
        v.step(0.01, clock.now)
    assert abs(v.up - 20.0) < 0.3
    for _ in range(300):  # to 6.5 s: the descent is under way
        v.step(0.01, clock.now)
    assert v.up < 19.0 and v.vu < -0.5


def test_fs_gcs_enable_2_is_named_at_arming_which_goes_ahead() -> None:
    """AP_Arming_Copter::parameter_checks reports it and does not refuse."""
    ap, _ = autopilot(FS_GCS_ENABLE=2)
    v = ap.vehicle
    v.origin_set = True
    assert v.set_mode(GUIDED) is None
    assert v.arm() == (MAV.MAV_RESULT_ACCEPTED, None)
    assert (MAV.MAV_SEVERITY_CRITICAL, "PreArm: FS_GCS_ENABLE=2 removed, see FS_OPTIONS") in v.texts
    ap1, _ = autopilot(FS_GCS_ENABLE=1)
    ap1.vehicle.origin_set = True
    ap1.vehicle.set_mode(GUIDED)
    assert ap1.vehicle.arm()[0] == MAV.MAV_RESULT_ACCEPTED
    assert not any("PreArm" in text for _, text in ap1.vehicle.texts)


# --- ArduCopter: FS_OPTIONS ---------------------------------------------------------------


def fly_a_mission(ap: Autopilot, last: int = NAV_WAYPOINT) -> None:
    """A mission of one waypoint far north (and ``last``), flown in AUTO."""
    v = ap.vehicle
    home = Item(NAV_WAYPOINT, 0, (0, 0, 0, 0), HOME[0], HOME[1], 0)
    far = Item(NAV_WAYPOINT, 3, (0, 0, 0, 0), HOME[0] + 0.01, HOME[1], 20)
    v.mission.items = [home, far, Item(last, 3, (0, 0, 0, 0), 0, 0, 0)]
    airborne(ap, AUTO)


#: (the mode flying, FS_OPTIONS) -> (the mode after the silence, what it says).
OPTION_CASES: dict[tuple[int, int], tuple[str, str]] = {
    (AUTO, 0): ("RTL", "GCS Failsafe"),
    (AUTO, 2): ("AUTO", "GCS Failsafe - Continuing Auto Mode"),
    (AUTO, 16): ("RTL", "GCS Failsafe"),  # AUTO is the autopilot's
    (GUIDED, 2): ("RTL", "GCS Failsafe"),  # no bit spares GUIDED
    (GUIDED, 4 | 16): ("RTL", "GCS Failsafe"),  # bit 2 is the radio's
    (LOITER, 16): ("LOITER", "GCS Failsafe - Continuing Pilot Control"),
    (BRAKE, 16): ("BRAKE", "GCS Failsafe - Continuing Pilot Control"),
    (POSHOLD, 16): ("POSHOLD", "GCS Failsafe - Continuing Pilot Control"),
    (LOITER, 0): ("RTL", "GCS Failsafe"),
    (LAND, 8): ("LAND", "GCS Failsafe - Continuing Landing"),
    (LAND, 0): ("RTL", "GCS Failsafe"),  # a landing is no exception by itself
    (LAND, 16): ("RTL", "GCS Failsafe"),  # LAND is the autopilot's
}


@pytest.mark.parametrize(("mode", "options"), sorted(OPTION_CASES))
def test_fs_options_make_the_exceptions_arducopter_makes(mode: int, options: int) -> None:
    ap, clock = autopilot(FS_GCS_ENABLE=1, FS_OPTIONS=options)
    if mode == AUTO:
        fly_a_mission(ap)
    else:
        airborne(ap, mode)
    after, text = OPTION_CASES[(mode, options)]
    assert silenced(ap, clock) == [text]
    assert mode_name(ap) == after


def test_the_default_fs_options_is_16_as_arducopter_ships() -> None:
    ap, _ = autopilot()
    assert ap.vehicle.params["FS_OPTIONS"] == 16


def test_an_auto_landing_goes_on_with_bit_3() -> None:
    """ModeAuto::is_landing: its NAV_LAND (the approach too)."""
    ap, clock = autopilot(FS_GCS_ENABLE=1, FS_OPTIONS=8)
    fly_a_mission(ap, last=NAV_LAND)
    v = ap.vehicle
    assert isinstance(v, Copter)
    v._auto_start_nav(2)  # the NAV_LAND begins
    assert silenced(ap, clock) == ["GCS Failsafe - Continuing Landing"]
    assert mode_name(ap) == "LAND"


@pytest.mark.parametrize(
    ("mode", "options", "released"),
    [(GUIDED, 32, True), (AUTO, 34, False), (LOITER, 48, False), (GUIDED, 0, False)],
)
def test_bit_5_releases_the_gripper_with_any_action_but_none(
    mode: int, options: int, released: bool
) -> None:
    ap, clock = autopilot(FS_GCS_ENABLE=1, FS_OPTIONS=options)
    if mode == AUTO:
        fly_a_mission(ap)
    else:
        airborne(ap, mode)
    said = silenced(ap, clock)
    assert ap.vehicle.payload_released is released
    assert ("Gripper load released" in said) is released


# --- ArduRover ---------------------------------------------------------------------------

#: FS_ACTION -> the mode after the silence, from GUIDED.
ROVER_ACTIONS: dict[int, str] = {
    0: "GUIDED",
    1: "RTL",
    2: "HOLD",
    3: "SMART_RTL",
    4: "SMART_RTL",
    6: "LOITER",
    7: "GUIDED",  # the switch has no default: nothing
}


@pytest.mark.parametrize("action", sorted(ROVER_ACTIONS))
def test_each_fs_action_does_what_ardurover_does(action: int) -> None:
    ap, clock = autopilot("boat", FS_ACTION=action)
    airborne(ap, ROVER_GUIDED)
    assert silenced(ap, clock) == ["GCS Failsafe"]
    assert mode_name(ap) == ROVER_ACTIONS[action]
    assert ap.vehicle.armed


def test_fs_action_5_terminates() -> None:
    ap, clock = autopilot("boat", FS_ACTION=5)
    airborne(ap, ROVER_GUIDED)
    silenced(ap, clock)
    assert not ap.vehicle.armed


def test_without_a_position_rtl_falls_back_to_hold() -> None:
    ap, clock = autopilot("boat", FS_ACTION=3)
    airborne(ap, MANUAL)
    ap.vehicle.gps_fix, ap.vehicle.satellites = 0, 0
    silenced(ap, clock)
    assert mode_name(ap) == "HOLD"


@pytest.mark.parametrize(("enable", "after"), [(1, "RTL"), (2, "AUTO")])
def test_fs_gcs_enable_2_lets_a_mission_in_auto_go_on(enable: int, after: str) -> None:
    ap, clock = autopilot("boat", FS_GCS_ENABLE=enable, FS_ACTION=1)
    v = ap.vehicle
    home = Item(NAV_WAYPOINT, 0, (0, 0, 0, 0), HOME[0], HOME[1], 0)
    v.mission.items = [home, Item(NAV_WAYPOINT, 3, (0, 0, 0, 0), HOME[0] + 0.001, HOME[1], 0)]
    airborne(ap, ROVER_AUTO)
    said = silenced(ap, clock)
    assert said[0] == "GCS Failsafe"
    assert ("Failsafe - Continuing Auto Mode" in said) is (enable == 2)
    assert mode_name(ap) == after


@pytest.mark.parametrize(("options", "acts"), [(0, False), (1, True)])
def test_in_hold_it_acts_only_with_fs_options_bit_0(options: int, acts: bool) -> None:
    ap, clock = autopilot("boat", FS_ACTION=1, FS_OPTIONS=options)
    airborne(ap, HOLD)
    said = silenced(ap, clock)
    assert (said == ["GCS Failsafe"]) is acts
    assert mode_name(ap) == ("RTL" if acts else "HOLD")


def test_in_rtl_it_never_acts() -> None:
    ap, clock = autopilot("boat", FS_ACTION=2)
    airborne(ap, ROVER_RTL)
    assert silenced(ap, clock) == []
    assert mode_name(ap) == "RTL" and not ap.gcs_failsafe
