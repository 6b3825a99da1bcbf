"""A small kinematic world for a simulated Raspberry Pi car.

The car adapter drives the very same gpiozero devices in simulation as on a Pi, only on
gpiozero's mock pins (:mod:`agents.vehicles.car.sim.pins`). This module is the physics
wired to those pins:

* a differential-drive model (:func:`~agents.vehicles.car.kinematics.diff_drive_step`)
  moved by the motor efforts read back from the pins;
* the car's pose as metres north/east of an origin (lat, lon) plus a compass heading;
* battery drain proportional to motor effort (an empty battery stops the wheels);
* obstacles (circles and axis-aligned boxes in local metres) that tests can place, move
  and remove; the car's body is a circle that cannot pass through them;
* the HC-SR04's view: the distance ray-cast to the nearest obstacle in its beam.

Threads: gpiozero reads the distance sensor in its own thread, so the ray cast runs
there while :meth:`CarWorld.step` runs on the asyncio loop; a lock guards the pose and
the obstacles. Everything else is single-threaded.

Conventions: ``north``/``east`` in metres from the origin; headings in degrees clockwise
from north, in [0, 360); a motor "effort" is in [-1, 1] (1 = full power forward).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, TypeAlias

from agents.geo import offset
from agents.vehicles.car.config import MotorWiring, PinName
from agents.vehicles.car.kinematics import Pose, diff_drive_step, normalize_heading
from agents.vehicles.car.sim.pins import (
    HC_SR04_BEAM_HALF_ANGLE_DEG,
    HC_SR04_MAX_RANGE_M,
    HC_SR04_MIN_RANGE_M,
    EchoPin,
    MotorInputs,
    RangingTriggerPin,
)

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


@dataclass
class Circle:
    """A round obstacle (a post, a bin): centre in local metres and radius."""

    north: float
    east: float
    radius: float


@dataclass
class Box:
    """An axis-aligned box obstacle (a wall, a crate): centre and full sizes in metres."""

    north: float
    east: float
    size_north: float
    size_east: float


Obstacle: TypeAlias = Circle | Box


def _ray_circle(on: float, oe: float, dn: float, de: float, c: Circle) -> float | None:
    # Solve |o + t d - c|^2 = r^2 for the smallest t >= 0 (d is a unit vector).
    rn, re_ = c.north - on, c.east - oe
    b = rn * dn + re_ * de
    q = rn * rn + re_ * re_ - c.radius * c.radius
    if q <= 0.0:
        return 0.0  # the ray starts inside the circle
    disc = b * b - q
    if disc < 0.0 or b <= 0.0:
        return None
    return b - math.sqrt(disc)


def _ray_box(on: float, oe: float, dn: float, de: float, box: Box) -> float | None:
    # Slab method: intersect the parameter intervals of the two axis slabs.
    t_near, t_far = 0.0, math.inf
    for o, d, centre, size in (
        (on, dn, box.north, box.size_north),
        (oe, de, box.east, box.size_east),
    ):
        lo, hi = centre - size / 2.0, centre + size / 2.0
        if abs(d) < 1e-12:
            if not lo <= o <= hi:
                return None
            continue
        t1, t2 = (lo - o) / d, (hi - o) / d
        if t1 > t2:
            t1, t2 = t2, t1
        t_near, t_far = max(t_near, t1), min(t_far, t2)
        if t_near > t_far:
            return None
    return t_near


def _penetration(north: float, east: float, radius: float, obstacle: Obstacle) -> float:
    """How deep a body circle at (north, east) overlaps ``obstacle`` (<= 0: apart)."""
    if isinstance(obstacle, Circle):
        gap = math.hypot(obstacle.north - north, obstacle.east - east)
        return radius + obstacle.radius - gap
    half_n, half_e = obstacle.size_north / 2.0, obstacle.size_east / 2.0
    nearest_n = min(max(north, obstacle.north - half_n), obstacle.north + half_n)
    nearest_e = min(max(east, obstacle.east - half_e), obstacle.east + half_e)
    return radius - math.hypot(nearest_n - north, nearest_e - east)


def obstacles_from_spec(spec: Iterable[Any]) -> list[Obstacle]:
    """Obstacles from a JSON-friendly list, as written in an agent's options.

    Each item is ``{"circle": [north, east, radius]}`` or
    ``{"box": [north, east, size_north, size_east]}`` (metres from the origin). Raises
    ValueError naming the item when one is malformed.
    """
    out: list[Obstacle] = []
    for i, item in enumerate(spec):
        try:
            if "circle" in item:
                n, e, r = (float(v) for v in item["circle"])
                if r <= 0:
                    raise ValueError("radius must be positive")
                out.append(Circle(n, e, r))
            elif "box" in item:
                n, e, sn, se = (float(v) for v in item["box"])
                if sn <= 0 or se <= 0:
                    raise ValueError("sizes must be positive")
                out.append(Box(n, e, sn, se))
            else:
                raise ValueError("expected a 'circle' or 'box' key")
        except (TypeError, ValueError) as exc:
            raise ValueError(f"obstacles[{i}]: {exc}") from None
    return out


# --------------------------------------------------------------------------------------
# The world
# --------------------------------------------------------------------------------------


class CarWorld:
    """One simulated car in its own little world of obstacles.

    ``factory`` is the gpiozero MockFactory the car's devices use (one per car, so
    several cars share nothing); ``left``/``right`` say which of its pins drive each
    motor. Construct the world, call :meth:`attach_distance_sensor` if the car has one,
    and only then create the gpiozero devices: they pick up the pins made here.

    The body is a circle of ``body_radius_m`` with the ultrasonic sensor at its front.
    ``max_speed_mps`` is a wheel's ground speed at full power and ``track_width_m`` the
    distance between the wheels. ``battery_drain_pct_per_s`` is the drain with both
    motors at full power; it scales with the mean absolute effort.
    """

    def __init__(
        self,
        factory: Any,
        *,
        left: MotorWiring,
        right: MotorWiring,
        origin: tuple[float, float],
        pose: Pose | None = None,
        max_speed_mps: float = 0.5,
        track_width_m: float = 0.15,
        body_radius_m: float = 0.12,
        battery_pct: float = 100.0,
        battery_drain_pct_per_s: float = 0.05,
        sensor_max_range_m: float = HC_SR04_MAX_RANGE_M,
        obstacles: Iterable[Obstacle] = (),
    ) -> None:
        if max_speed_mps <= 0 or track_width_m <= 0 or body_radius_m <= 0:
            raise ValueError("max_speed_mps, track_width_m and body_radius_m must be > 0")
        self.factory = factory
        self.origin = origin
        self.max_speed_mps = max_speed_mps
        self.track_width_m = track_width_m
        self.body_radius_m = body_radius_m
        self.battery_drain_pct_per_s = battery_drain_pct_per_s
        self.sensor_max_range_m = min(sensor_max_range_m, HC_SR04_MAX_RANGE_M)
        self._left = MotorInputs(factory, left)
        self._right = MotorInputs(factory, right)
        self._lock = threading.RLock()
        self._pose = pose or Pose()
        self._obstacles: list[Obstacle] = list(obstacles)
        self._battery = float(battery_pct)
        self._speed = 0.0
        self._efforts = (0.0, 0.0)
        self._in_contact = False
        self.collisions = 0  # contacts begun since the world was made
        self.distance_sensor_pins: tuple[RangingTriggerPin, EchoPin] | None = None

    # --- wiring -----------------------------------------------------------------------
    def attach_distance_sensor(self, trigger: PinName, echo: PinName) -> None:
        """Wire a simulated HC-SR04 to ``trigger``/``echo`` on this world's factory.

        Must run before gpiozero's DistanceSensor is created on those pins. Raises
        ValueError if the pins already exist as ordinary mock pins.
        """
        echo_pin = self.factory.pin(echo, pin_class=EchoPin)
        trigger_pin = self.factory.pin(
            trigger, pin_class=RangingTriggerPin, echo_pin=echo_pin, ranger=self.range_ahead
        )
        if not isinstance(echo_pin, EchoPin) or not isinstance(trigger_pin, RangingTriggerPin):
            raise ValueError(f"pins {trigger}/{echo} are already in use as other mock pins")
        self.distance_sensor_pins = (trigger_pin, echo_pin)

    # --- reading the world ------------------------------------------------------------
    @property
    def pose(self) -> Pose:
        with self._lock:
            return self._pose

    @property
    def position(self) -> tuple[float, float]:
        """(lat, lon) of the car's centre."""
        pose = self.pose
        return offset(self.origin, pose.north_m, pose.east_m)

    @property
    def heading_deg(self) -> float:
        return self.pose.heading_deg

    @property
    def speed_mps(self) -> float:
        """Ground speed over the last step (0 when stopped or blocked)."""
        return self._speed

    @property
    def battery_pct(self) -> float:
        return self._battery

    @property
    def efforts(self) -> tuple[float, float]:
        """(left, right) motor efforts read from the pins at the last step."""
        return self._efforts

    @property
    def in_contact(self) -> bool:
        """Whether the body touched an obstacle at the last step."""
        return self._in_contact

    @property
    def obstacles(self) -> list[Obstacle]:
        """A copy of the obstacle list (use the methods below to change it)."""
        with self._lock:
            return list(self._obstacles)

    def read_efforts(self) -> tuple[float, float]:
        """(left, right) efforts as the motor driver inputs are now."""
        return (self._left.effort(), self._right.effort())

    def sensor_origin(self) -> tuple[float, float]:
        """(north, east) of the ultrasonic sensor: the front of the body."""
        pose = self.pose
        h = math.radians(pose.heading_deg)
        return (
            pose.north_m + self.body_radius_m * math.cos(h),
            pose.east_m + self.body_radius_m * math.sin(h),
        )

    def point_ahead(self, distance_m: float, *, bearing_deg: float = 0.0) -> tuple[float, float]:
        """(north, east) ``distance_m`` in front of the sensor (``bearing_deg`` off the
        heading, clockwise)."""
        with self._lock:
            sn, se = self.sensor_origin()
            h = math.radians(self._pose.heading_deg + bearing_deg)
        return (sn + distance_m * math.cos(h), se + distance_m * math.sin(h))

    def range_ahead(self) -> float | None:
        """What an HC-SR04 on the front reads now: the distance in metres to the
        nearest obstacle surface inside its beam, at least 2 cm; None past its range.

        Called from gpiozero's sensor thread (through RangingTriggerPin).
        """
        with self._lock:
            sn, se = self.sensor_origin()
            heading = self._pose.heading_deg
            obstacles = list(self._obstacles)
        best: float | None = None
        # Five rays across the beam: a post slightly off-centre still echoes.
        for k in (-1.0, -0.5, 0.0, 0.5, 1.0):
            h = math.radians(heading + k * HC_SR04_BEAM_HALF_ANGLE_DEG)
            dn, de = math.cos(h), math.sin(h)
            for obstacle in obstacles:
                if isinstance(obstacle, Circle):
                    t = _ray_circle(sn, se, dn, de, obstacle)
                else:
                    t = _ray_box(sn, se, dn, de, obstacle)
                if t is not None and (best is None or t < best):
                    best = t
        if best is None or best > self.sensor_max_range_m:
            return None
        return max(best, HC_SR04_MIN_RANGE_M)

    # --- changing the world -----------------------------------------------------------
    def add_obstacle(self, obstacle: Obstacle) -> Obstacle:
        """Place ``obstacle``; returns it (to move or remove later)."""
        with self._lock:
            self._obstacles.append(obstacle)
        return obstacle

    def place_obstacle_ahead(self, distance_m: float, *, radius_m: float = 0.05) -> Circle:
        """Place a post whose near surface is ``distance_m`` in front of the sensor."""
        with self._lock:
            north, east = self.point_ahead(distance_m + radius_m)
            circle = Circle(north, east, radius_m)
            self._obstacles.append(circle)
        return circle

    def move_obstacle(self, obstacle: Obstacle, north: float, east: float) -> None:
        """Move ``obstacle``'s centre to (north, east)."""
        with self._lock:
            obstacle.north, obstacle.east = north, east

    def remove_obstacle(self, obstacle: Obstacle) -> None:
        """Take ``obstacle`` away; raises ValueError if it is not in this world."""
        with self._lock:
            self._obstacles.remove(obstacle)

    def clear_obstacles(self) -> None:
        with self._lock:
            self._obstacles.clear()

    def set_pose(self, pose: Pose) -> None:
        """Put the car somewhere else (a test or demo set-up step)."""
        with self._lock:
            self._pose = Pose(pose.north_m, pose.east_m, normalize_heading(pose.heading_deg))

    # --- time -------------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance the world by ``dt`` seconds with the motor inputs as they are now.

        The body moves as far along its path as it can without entering an obstacle: it
        stops at contact (and a new contact is counted in :attr:`collisions`); turning
        in place and backing away stay possible.
        """
        if dt <= 0:
            return
        left, right = self.read_efforts()
        self._efforts = (left, right)
        # No charge, no torque: the driver's inputs still say "go" but nothing moves.
        power = 1.0 if self._battery > 0.0 else 0.0
        self._battery = max(
            0.0, self._battery - self.battery_drain_pct_per_s * (abs(left) + abs(right)) / 2 * dt
        )
        with self._lock:
            start = self._pose
            target = diff_drive_step(
                start,
                left * self.max_speed_mps * power,
                right * self.max_speed_mps * power,
                track_width_m=self.track_width_m,
                dt=dt,
            )
            allowed = max(0.0, self._depth(start.north_m, start.east_m))
            fraction = 1.0
            if self._depth(target.north_m, target.east_m) > allowed + 1e-9:
                fraction = self._free_fraction(start, target, allowed)
            moved = Pose(
                start.north_m + (target.north_m - start.north_m) * fraction,
                start.east_m + (target.east_m - start.east_m) * fraction,
                target.heading_deg,  # a round body can always turn where it stands
            )
            self._pose = moved
        self._speed = math.hypot(moved.north_m - start.north_m, moved.east_m - start.east_m) / dt
        contact = fraction < 1.0
        if contact and not self._in_contact:
            self.collisions += 1
            logger.warning(
                "simulated car hit an obstacle at %.2f m N, %.2f m E",
                moved.north_m,
                moved.east_m,
            )
        self._in_contact = contact

    def _depth(self, north: float, east: float) -> float:
        return max(
            (_penetration(north, east, self.body_radius_m, o) for o in self._obstacles),
            default=-math.inf,
        )

    def _free_fraction(self, start: Pose, target: Pose, allowed: float) -> float:
        # Bisect for the largest fraction of the step that keeps the body out of the
        # obstacles (or no deeper in than it already was): "stops at contact".
        lo, hi = 0.0, 1.0
        for _ in range(20):
            mid = (lo + hi) / 2.0
            n = start.north_m + (target.north_m - start.north_m) * mid
            e = start.east_m + (target.east_m - start.east_m) * mid
            if self._depth(n, e) > allowed + 1e-9:
                hi = mid
            else:
                lo = mid
        return lo

    async def run(self, hz: float = 50.0) -> None:
        """Step the world at ``hz`` with the real elapsed time until cancelled.

        A step never covers more than 0.1 s, so a stalled event loop slows the
        simulation down instead of teleporting the car through a wall.
        """
        period = 1.0 / hz
        last = time.monotonic()
        while True:
            await asyncio.sleep(period)
            now = time.monotonic()
            try:
                self.step(min(now - last, 0.1))
            except Exception:  # keep the world alive; a dead world is a frozen car
                logger.exception("car world step failed")
            last = now
