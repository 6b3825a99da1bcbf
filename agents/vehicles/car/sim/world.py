"""A small kinematic world for simulated Raspberry Pi cars.

The car adapter drives the very same gpiozero devices in simulation as on a Pi, only on
gpiozero's mock pins. This module is the "physics" wired to those pins:

* a differential-drive model that reads the motor driver inputs back from the mock pins
  (PWM duty cycles and direction levels), so what moves the simulated car is exactly
  what gpiozero told the motor driver;
* the car's pose as metres north/east of an origin (lat, lon) plus a compass heading;
* battery drain proportional to motor effort (an empty battery stops the wheels);
* obstacles (circles and axis-aligned boxes in local metres) that tests can place, move
  and remove; the car's body is a circle that cannot pass through them;
* an HC-SR04 on the front: :class:`RangingTriggerPin` answers each trigger pulse of
  gpiozero's ``DistanceSensor`` with an echo pulse ``2 * distance / 343.26`` s long,
  where the distance is ray-cast to the nearest obstacle in the sensor's beam at the
  moment of the ping (no echo, i.e. the sensor's 38 ms time-out pulse, past 4 m).

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
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, TypeAlias

from gpiozero.pins.mock import (  # type: ignore[import-untyped, unused-ignore]
    MockPWMPin,
    MockTriggerPin,
)

from agents.geo import offset

logger = logging.getLogger(__name__)

#: The speed of sound gpiozero's DistanceSensor converts echo times with (m/s).
SPEED_OF_SOUND_MPS = 343.26
#: HC-SR04 datasheet: 2 cm to 4 m, a beam of about 15 degrees, and an echo line that
#: stays high for about 38 ms when nothing answers.
HC_SR04_MIN_RANGE_M = 0.02
HC_SR04_MAX_RANGE_M = 4.0
HC_SR04_BEAM_HALF_ANGLE_DEG = 7.5
HC_SR04_NO_ECHO_S = 0.038
#: Delay between the end of the trigger pulse and the echo rising (the sensor first
#: sends its 8-cycle 40 kHz burst).
HC_SR04_BURST_S = 0.0005

#: A GPIO pin as gpiozero names it: a BCM number (17) or a name ("GPIO17", "BOARD11").
PinName: TypeAlias = int | str


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pose:
    """Where the car is: metres north/east of the origin, compass heading in degrees."""

    north_m: float = 0.0
    east_m: float = 0.0
    heading_deg: float = 0.0


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


def normalize_heading(deg: float) -> float:
    """``deg`` folded into [0, 360)."""
    out = deg % 360.0
    return 0.0 if out >= 360.0 else out  # -1e-17 % 360 == 360.0 in floating point


def diff_drive_step(
    pose: Pose, left_mps: float, right_mps: float, *, track_width_m: float, dt: float
) -> Pose:
    """Advance a differential-drive (skid-steer) vehicle by ``dt`` seconds.

    ``left_mps``/``right_mps`` are the wheel ground speeds (negative: backwards). The
    vehicle moves at their mean along its heading and turns at their difference over the
    track width; the heading is integrated at the interval's midpoint, which is accurate
    to well under a millimetre per step at 50 Hz. Returns the new pose.
    """
    v = (left_mps + right_mps) / 2.0
    # Positive omega turns anticlockwise (left), i.e. decreases the compass heading.
    omega = (right_mps - left_mps) / track_width_m
    turn_deg = math.degrees(omega * dt)
    mid = math.radians(pose.heading_deg - turn_deg / 2.0)
    return Pose(
        north_m=pose.north_m + v * dt * math.cos(mid),
        east_m=pose.east_m + v * dt * math.sin(mid),
        heading_deg=normalize_heading(pose.heading_deg - turn_deg),
    )


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
# Mock pins wired to the world
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DualPinMotorWiring:
    """An H-bridge driven by two PWM inputs (L298N, L9110S, CamJam EduKit 3 board), with
    an optional enable input when it is not jumpered high (gpiozero ``Motor``)."""

    forward: PinName
    backward: PinName
    enable: PinName | None = None


@dataclass(frozen=True)
class PhaseEnableMotorWiring:
    """A phase/enable driver (DRV8835 in PHASE/ENABLE mode; gpiozero
    ``PhaseEnableMotor``): the phase level selects the direction, enable's PWM the
    power."""

    phase: PinName
    enable: PinName


MotorWiring: TypeAlias = DualPinMotorWiring | PhaseEnableMotorWiring


class _MotorInputs:
    """The driver inputs of one motor, read back as an effort in [-1, 1]."""

    def __init__(self, factory: Any, wiring: MotorWiring) -> None:
        # Pins are created (as PWM-capable mock pins) or looked up once; gpiozero's
        # devices later get these very objects from the same factory.
        self.wiring = wiring
        self._b: Any
        self._en: Any
        if isinstance(wiring, DualPinMotorWiring):
            self._a = factory.pin(wiring.forward)
            self._b = factory.pin(wiring.backward)
            self._en = None if wiring.enable is None else factory.pin(wiring.enable)
        else:
            self._a = factory.pin(wiring.phase)
            self._b = None
            self._en = factory.pin(wiring.enable)

    def effort(self) -> float:
        if self._b is not None:  # dual-pin H-bridge
            value = float(self._a.state) - float(self._b.state)
            if self._en is not None:
                value *= float(self._en.state)
        else:  # phase/enable: phase high means backwards
            value = float(self._en.state) * (-1.0 if self._a.state else 1.0)
        return max(-1.0, min(1.0, value))


class EchoPin(MockPWMPin):  # type: ignore[misc]
    """The HC-SR04 ECHO line as a mock input pin whose edges can carry exact times.

    gpiozero's DistanceSensor times the echo pulse from the timestamps of the pin's
    edges. Mock pins stamp an edge with the time the driving thread got round to it,
    and under the GIL that can be milliseconds late (a millisecond is 17 cm of range):
    good enough for a demo, too noisy for tests of a 25 cm stop distance. Real pins
    read by pigpio's DMA sampler are accurate to microseconds, so the simulation stamps
    the falling edge exactly ``echo_time`` after the rising one.

    It subclasses MockPWMPin only so that a MockFactory whose default pin class is
    MockPWMPin accepts it when the DistanceSensor asks for the pin.
    """

    def __init__(self, factory: Any, info: Any) -> None:
        super().__init__(factory, info)
        self._stamp: float | None = None

    def drive_at(self, level: bool, ticks: float) -> None:
        """Drive the (input) pin to ``level`` with the edge stamped at ``ticks``."""
        self._stamp = ticks
        try:
            if level:
                self.drive_high()
            else:
                self.drive_low()
        finally:
            self._stamp = None

    def _change_state(self, value: Any) -> bool:
        changed: bool = super()._change_state(value)
        if changed and self._stamp is not None:
            # MockPin reports _last_change to the edge callback as the edge's ticks.
            self._last_change = self._stamp
        return changed


class RangingTriggerPin(MockTriggerPin, MockPWMPin):  # type: ignore[misc]
    """The HC-SR04 TRIG line: each trigger pulse is answered on ``echo_pin`` with a
    pulse ``2 * distance / SPEED_OF_SOUND_MPS`` long, ``distance`` coming from
    ``ranger()`` at the moment of the ping (None: nothing in range, a 38 ms pulse).

    This is gpiozero's MockTriggerPin with a live echo time. Like EchoPin it is also a
    MockPWMPin so a MockFactory(pin_class=MockPWMPin) hands it to the sensor.
    """

    def __init__(
        self,
        factory: Any,
        info: Any,
        echo_pin: EchoPin,
        ranger: Callable[[], float | None],
    ) -> None:
        super().__init__(factory, info, echo_pin=echo_pin, echo_time=HC_SR04_NO_ECHO_S)
        self.ranger = ranger

    def _echo(self) -> None:  # runs in MockTriggerPin's per-ping thread
        try:
            distance = self.ranger()
        except Exception:  # a broken ranger must not kill the sensor thread silently
            logger.exception("simulated distance sensor failed to range")
            distance = None
        self.echo_time = (
            HC_SR04_NO_ECHO_S if distance is None else 2.0 * distance / SPEED_OF_SOUND_MPS
        )
        time.sleep(HC_SR04_BURST_S)
        rise = time.monotonic()
        self.echo_pin.drive_at(True, rise)
        time.sleep(self.echo_time)
        self.echo_pin.drive_at(False, rise + self.echo_time)


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
        self._left = _MotorInputs(factory, left)
        self._right = _MotorInputs(factory, right)
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
