"""ArduPilot's kinematic shaping, as the simulated copter moves: a jerk-limited path
from the current velocity and acceleration to the one a mode asks for.

ArduCopter's position controller (``libraries/AC_AttitudeControl/AC_PosControl.cpp``)
never hands a flight mode's target straight to the motors: ``input_vel_accel_*`` and
``input_pos_xyz`` shape it first (``libraries/AP_Math/control.cpp``: ``shape_accel``,
``shape_vel_accel``, ``shape_vel_accel_xy``, ``sqrt_controller``), within the mode's
acceleration limit (GUIDED: ``WPNAV_ACCEL`` horizontally, ``WPNAV_ACCEL_Z``
vertically) and the jerk limit (``PSC_JERK_XY``, ``PSC_JERK_Z``). That shaping is why a
copter climbing at 2.5 m/s needs some 3.4 m to stop at the default 1 m/s²: these are
the same functions, in m, m/s and s, for one axis and for the horizontal plane.
"""

from __future__ import annotations

import math

Vector = tuple[float, float]


def sqrt_controller(error: float, p: float, second_ord_lim: float, dt: float) -> float:
    """ArduPilot's ``sqrt_controller``: proportional near zero, then the square root
    that keeps the second derivative within ``second_ord_lim``; never more than the
    error can absorb in one ``dt``."""
    if second_ord_lim <= 0:
        rate = error * p
    elif p == 0:
        rate = math.copysign(math.sqrt(2.0 * second_ord_lim * abs(error)), error)
    else:
        linear = second_ord_lim / (p * p)
        if error > linear:
            rate = math.sqrt(2.0 * second_ord_lim * (error - linear / 2.0))
        elif error < -linear:
            rate = -math.sqrt(2.0 * second_ord_lim * (-error - linear / 2.0))
        else:
            rate = error * p
    if dt > 0:
        bound = abs(error) / dt
        rate = max(-bound, min(bound, rate))
    return rate


def sqrt_controller_xy(error: Vector, p: float, second_ord_lim: float, dt: float) -> Vector:
    """:func:`sqrt_controller` on the length of a horizontal error."""
    length = math.hypot(*error)
    if length <= 0:
        return (0.0, 0.0)
    scale = sqrt_controller(length, p, second_ord_lim, dt) / length
    return (error[0] * scale, error[1] * scale)


def shape_vel_accel(
    vel_input: float,
    vel: float,
    accel: float,
    accel_min: float,
    accel_max: float,
    jerk_max: float,
    dt: float,
) -> float:
    """One axis: the acceleration after ``dt`` on the jerk-limited way from ``vel``
    (accelerating at ``accel``) to ``vel_input``, within ``accel_min``..``accel_max``."""
    error = vel_input - vel
    kpa = jerk_max / (accel_max if error > 0 else -accel_min)
    target = sqrt_controller(error, kpa, jerk_max, dt)
    target = max(accel_min, min(accel_max, target))
    step = jerk_max * dt
    return accel + max(-step, min(step, target - accel))


def shape_vel_accel_xy(
    vel_input: Vector, vel: Vector, accel: Vector, accel_max: float, jerk_max: float, dt: float
) -> Vector:
    """The horizontal plane: as :func:`shape_vel_accel`, the acceleration's length
    within ``accel_max`` and its change within ``jerk_max``."""
    error = (vel_input[0] - vel[0], vel_input[1] - vel[1])
    target = sqrt_controller_xy(error, jerk_max / accel_max, jerk_max, dt)
    target = limit_length(target, accel_max)
    delta = limit_length((target[0] - accel[0], target[1] - accel[1]), jerk_max * dt)
    return (accel[0] + delta[0], accel[1] + delta[1])


def position_speed(error: float, accel_max: float, jerk_max: float, dt: float) -> float:
    """The speed towards a position ``error`` metres away, as ``shape_pos_vel_accel``
    asks for it: half the acceleration limit for the approach, so that the shaping of
    the velocity has room to stop there without overshooting."""
    return sqrt_controller(error, 0.5 * jerk_max / accel_max, 0.5 * accel_max, dt)


def position_velocity_xy(error: Vector, accel_max: float, jerk_max: float, dt: float) -> Vector:
    """:func:`position_speed` for a horizontal position error."""
    return sqrt_controller_xy(error, 0.5 * jerk_max / accel_max, 0.5 * accel_max, dt)


def limit_length(v: Vector, limit: float) -> Vector:
    """``v`` shortened to ``limit`` if longer."""
    length = math.hypot(*v)
    if length <= limit or length == 0:
        return v
    return (v[0] * limit / length, v[1] * limit / length)


def stopping_distance(speed: float, accel_max: float, jerk_max: float) -> float:
    """How far a velocity shaped as above goes from ``speed`` to rest: the braking at
    ``accel_max`` and the ramp up to it at ``jerk_max``."""
    speed = abs(speed)
    return speed * speed / (2.0 * accel_max) + speed * accel_max / (2.0 * jerk_max)
