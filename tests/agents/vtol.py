"""The simulated Spektrum VTOL as the tests fly it, in the agent's tests (test_spektrum)
and on a running platform (tests/integration/test_vtol_platform.py)."""

from __future__ import annotations

#: A nimble model, so that flights fit in a test.
FAST = {
    "max_climb_mps": 8.0,
    "max_descent_mps": 8.0,
    "transition_s": 0.5,
    "min_transition_altitude_m": 5.0,
    "land_ramp_per_s": 1.0,
}
#: The commands the tests' tasks allow (the sticks, the modes, arm and disarm).
VTOL_COMMANDS = (
    "arm", "disarm", "throttle_up", "throttle_down", "yaw_left", "yaw_right", "pitch_up",
    "pitch_down", "roll_left", "roll_right", "change_to_vtol_mode", "change_to_aircraft_mode",
)  # fmt: skip
