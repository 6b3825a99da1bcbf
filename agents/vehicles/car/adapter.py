"""Adapter for the paper's Raspberry Pi cars (section 4.2.1), driven through gpiozero.

Hardware, all optional parts declared in the options (see ``docs/vehicles/car.md``):

* two DC motors (left and right wheels) on an H-bridge, as a gpiozero ``Robot`` of two
  ``Motor`` (two PWM inputs per motor: L298N, L9110S, CamJam EduKit 3) or two
  ``PhaseEnableMotor`` (DRV8835): forward, backward, spin left/right, stop;
* a pan/tilt camera arm on two ``AngularServo`` with about 180 degrees of travel each;
* an HC-SR04 ultrasonic ``DistanceSensor`` on the front. A watch loop (>= 20 Hz) stops
  the car as soon as an obstacle is nearer than ``obstacle_stop_m`` while it drives
  forwards, and ``forward`` is refused (code ``obstacle``) while it is; backing away
  and turning stay allowed.

The devices sit on a gpiozero pin factory: a real one on a Pi (``pin_factory`` names it,
else the first that loads), or one handed over as an object, as the simulator
(:mod:`agents.vehicles.car.sim`) hands over its mock pins. The car has no GPS: position
and heading are dead-reckoned from the motor commands when ``origin`` is configured
(and unknown otherwise), and the battery level is unknown, unless a ``sensors`` object
knows better (:class:`~agents.vehicles.car.config.CarSensors`: the simulated world).

Speeds are fractions of full motor power (0..1), not m/s: ``max_speed_mps`` converts
them for telemetry, dead reckoning and :meth:`CarAdapter.project`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import time
import warnings
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any

# gpiozero ships no type hints ("unused-ignore": the project config may already
# ignore missing imports).
import gpiozero  # type: ignore[import-untyped, unused-ignore]

from agents.geo import offset
from agents.telemetry import TopicInfo
from agents.vehicles.base import (
    Adapter,
    AdapterError,
    CommandSpec,
    Projection,
    VehicleState,
)
from agents.vehicles.car.config import CarConfig, DualPinMotorWiring, MotorWiring, PinName
from agents.vehicles.car.kinematics import Pose, diff_drive_step
from agents.vehicles.car.vocabulary import TELEMETRY_TOPICS, car_vocabulary

logger = logging.getLogger(__name__)

#: gpiozero's own order of preference for real pin factories.
REAL_PIN_FACTORIES = ("lgpio", "rpigpio", "pigpio", "native")


def _load_pin_factory(name: str | None) -> Any:
    """A real gpiozero pin factory: ``name``, else $GPIOZERO_PIN_FACTORY, else the first
    of :data:`REAL_PIN_FACTORIES` that loads. Raises RuntimeError listing why each
    failed (typically: not a Raspberry Pi, or the GPIO library is missing)."""
    env = os.environ.get("GPIOZERO_PIN_FACTORY")
    names = [name] if name else [env] if env else list(REAL_PIN_FACTORIES)
    available = {ep.name: ep for ep in entry_points(group="gpiozero_pin_factories")}
    errors: list[str] = []
    for candidate in names:
        ep = available.get(candidate.lower())
        if ep is None:
            errors.append(f"{candidate}: no such gpiozero pin factory")
            continue
        try:
            return ep.load()()
        except Exception as exc:
            errors.append(f"{candidate}: {exc}")
    raise RuntimeError("; ".join(errors))


# --------------------------------------------------------------------------------------
# The adapter
# --------------------------------------------------------------------------------------


class CarAdapter(Adapter):
    """The Raspberry Pi car. Options: see :class:`CarConfig` and ``docs/vehicles/car.md``.

    Construction only checks the options (ValueError on a bad one); :meth:`start` opens
    the GPIO devices (AdapterError ``hardware`` if it cannot) and starts the obstacle
    watch.

    Public attributes for diagnostics and tests, None until started or when absent:
    ``robot``, ``pan_servo``, ``tilt_servo``, ``sensor`` (the gpiozero devices),
    ``pin_factory`` and ``sensors`` (the ``sensors`` option).
    """

    name = "car"
    safe_action_words = dict.fromkeys(("stop", "land", "return_to_home"), "stop where it is")
    telemetry_labels = {
        "distance_ahead": TopicInfo("Obstacle ahead", "m", 2),
        "camera_pan": TopicInfo("Camera pan", "°", 0),
        "camera_tilt": TopicInfo("Camera tilt", "°", 0),
        "motors": TopicInfo("Motor power (left, right)", decimals=2),
    }

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = CarConfig.from_options(options)
        self.pin_factory: Any = None
        self.sensors = self.config.sensors
        self.robot: Any = None
        self.pan_servo: Any = None
        self.tilt_servo: Any = None
        self.sensor: Any = None
        self.obstacle_stops = 0  # times the watch loop stopped the car
        self._own_factory = False
        self._tasks: list[asyncio.Task[None]] = []
        self._distance: float | None = None
        # Dead reckoning on a real car (no GPS): starts at the configured origin.
        self._odometry = Pose(heading_deg=self.config.heading_deg)
        self._odometry_t: float | None = None

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        """Open the devices, wait (up to 2 s) for the first distance reading and start the
        watch loop. Raises AdapterError ``hardware`` when no pin factory loads (not a Pi:
        run the car on its simulator with ``python -m agents sim fleet``) or a device
        cannot be opened."""
        if self.robot is not None:
            return
        cfg = self.config
        factory: Any = cfg.pin_factory
        if factory is None or isinstance(factory, str):
            try:
                factory = _load_pin_factory(factory)
            except RuntimeError as exc:
                raise AdapterError(
                    f"no usable GPIO: {exc} (no Raspberry Pi here? `python -m agents sim "
                    "fleet` runs the car on its simulator)",
                    code="hardware",
                ) from None
            self._own_factory = True
        self.pin_factory = factory

        try:
            self._open_devices(factory)
        except Exception as exc:
            await self.close()
            raise AdapterError(
                f"cannot open the car's GPIO devices: {exc}", code="hardware"
            ) from exc

        if self.sensor is not None:
            deadline = time.monotonic() + 2.0
            # Readiness is two threading.Events set in gpiozero's sensor thread;
            # polling them is simpler than bridging both into asyncio.
            while not self._sensor_ready() and time.monotonic() < deadline:  # noqa: ASYNC110
                await asyncio.sleep(0.02)
            if self._read_distance() is None:
                logger.warning("distance sensor gave no reading yet; forward stays refused")
        self._tasks.append(asyncio.create_task(self._watch(), name="car-watch"))

    def _open_devices(self, factory: Any) -> None:
        cfg = self.config

        def motor(wiring: MotorWiring) -> Any:
            if isinstance(wiring, DualPinMotorWiring):
                return gpiozero.Motor(
                    wiring.forward, wiring.backward, enable=wiring.enable, pin_factory=factory
                )
            return gpiozero.PhaseEnableMotor(wiring.phase, wiring.enable, pin_factory=factory)

        left = motor(cfg.left)
        try:
            self.robot = gpiozero.Robot(left, motor(cfg.right), pin_factory=factory)
        except Exception:
            left.close()  # not yet owned by a Robot that close() would find
            raise
        if cfg.camera_arm:
            self.pan_servo = self._servo(cfg.camera_pan_pin, cfg.camera_pan_reversed)
            self.tilt_servo = self._servo(cfg.camera_tilt_pin, cfg.camera_tilt_reversed)
        if cfg.distance_sensor:
            with warnings.catch_warnings():
                if not self._own_factory:
                    # Advice to use pigpio for accurate timing: moot on a factory handed
                    # over (the simulator's mock pins).
                    warnings.simplefilter("ignore", gpiozero.PWMSoftwareFallback)
                self.sensor = gpiozero.DistanceSensor(
                    echo=cfg.distance_echo_pin,
                    trigger=cfg.distance_trigger_pin,
                    queue_len=cfg.distance_queue_len,
                    max_distance=cfg.distance_max_m,
                    threshold_distance=min(cfg.obstacle_stop_m, cfg.distance_max_m),
                    pin_factory=factory,
                )

    def _servo(self, pin: PinName, reversed_: bool) -> Any:
        cfg = self.config
        half = cfg.camera_range_deg / 2
        # A servo mounted the other way round: swap the angle ends, keep our convention
        # (pan positive to the right, tilt positive upwards).
        lo, hi = (half, -half) if reversed_ else (-half, half)
        return gpiozero.AngularServo(
            pin,
            initial_angle=0.0,
            min_angle=lo,
            max_angle=hi,
            min_pulse_width=cfg.servo_min_pulse_s,
            max_pulse_width=cfg.servo_max_pulse_s,
            pin_factory=self.pin_factory,
        )

    async def close(self) -> None:
        """Stop the motors, stop the loops and close every gpiozero device (releasing
        its pins), then a real pin factory. Safe to call more than once."""
        if self.robot is not None:  # motors first, before anything that could fail
            with contextlib.suppress(Exception):
                self.robot.stop()
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks.clear()
        # Closing the sensor joins gpiozero's reading thread: up to ~0.1 s mid-ping.
        for attr in ("sensor", "tilt_servo", "pan_servo", "robot"):
            device = getattr(self, attr)
            if device is not None:
                try:
                    device.close()
                except Exception:
                    logger.exception("closing the car's %s failed", attr)
                setattr(self, attr, None)
        if self._own_factory and self.pin_factory is not None:
            with contextlib.suppress(Exception):
                self.pin_factory.close()
            self.pin_factory = None
            self._own_factory = False
        self._distance = None

    # --- vocabulary -----------------------------------------------------------------
    def commands(self) -> list[CommandSpec]:
        """Driving commands, plus the camera arm's when ``camera_arm`` is set."""
        return car_vocabulary(self.config)

    def telemetry_topics(self) -> list[str]:
        return list(TELEMETRY_TOPICS)

    # --- reading ----------------------------------------------------------------------
    def _motor_values(self) -> tuple[float, float] | None:
        if self.robot is None:
            return None
        left, right = self.robot.value
        return (float(left), float(right))

    def _pose(self) -> tuple[tuple[float, float] | None, float | None]:
        """((lat, lon) or None, heading or None) from the sensors or dead reckoning."""
        if self.sensors is not None:
            return self.sensors.position, self.sensors.heading_deg
        if self.config.origin is None:
            return None, None
        pose = self._odometry
        return offset(self.config.origin, pose.north_m, pose.east_m), pose.heading_deg

    def _speed_mps(self) -> float | None:
        if self.sensors is not None:
            return self.sensors.speed_mps
        values = self._motor_values()
        if values is None:
            return None
        return abs(values[0] + values[1]) / 2 * self.config.max_speed_mps

    def state(self) -> VehicleState:
        """Position and heading (from the sensors, or dead-reckoned from ``origin``; None
        when unknown), ground speed, and battery (from the sensors only)."""
        position, heading = self._pose()
        return VehicleState(
            lat=None if position is None else position[0],
            lon=None if position is None else position[1],
            heading_deg=heading,
            speed_mps=self._speed_mps(),
            battery=self._battery(),
        )

    def telemetry(self) -> dict[str, Any]:
        """Every topic of :data:`TELEMETRY_TOPICS`; None where unknown or absent."""
        position, heading = self._pose()
        speed = self._speed_mps()
        motors = self._motor_values()
        return {
            "battery_level": None if (battery := self._battery()) is None else round(battery, 2),
            "location": None
            if position is None
            else {"lat": round(position[0], 7), "lon": round(position[1], 7)},
            "heading": None if heading is None else round(heading, 1),
            "speed": None if speed is None else round(speed, 3),
            "distance_ahead": None if self._distance is None else round(self._distance, 3),
            "camera_pan": self._servo_angle(self.pan_servo),
            "camera_tilt": self._servo_angle(self.tilt_servo),
            "motors": None
            if motors is None
            else {"left": round(motors[0], 3), "right": round(motors[1], 3)},
        }

    def _battery(self) -> float | None:
        return None if self.sensors is None else self.sensors.battery_pct

    @staticmethod
    def _servo_angle(servo: Any) -> float | None:
        if servo is None:
            return None
        angle = servo.angle
        return None if angle is None else round(float(angle), 1)

    def _sensor_ready(self) -> bool:
        # The sensor's first value blocks until its queue has filled; once it has, one
        # of its in/out-of-range events is set. Checking them never blocks.
        sensor = self.sensor
        return sensor is not None and bool(
            sensor.wait_for_in_range(0) or sensor.wait_for_out_of_range(0)
        )

    def _read_distance(self) -> float | None:
        if not self._sensor_ready():
            return None
        self._distance = float(self.sensor.distance)
        return self._distance

    # --- acting -----------------------------------------------------------------------
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Carry out a car command. Raises AdapterError ``obstacle`` for ``forward``
        with an obstacle nearer than ``obstacle_stop_m``, ``sensor_fault`` for
        ``forward`` while the distance sensor has not given a reading, ``not_ready``
        before :meth:`start`, ``unknown_command`` for a name not in the vocabulary."""
        if self.robot is None:
            raise AdapterError("the car is not started", code="not_ready")
        if name in ("forward", "backward", "left", "right"):
            default = self.config.turn_power if name in ("left", "right") else 0.5
            speed = min(1.0, max(0.0, float(args.get("speed", default))))
            if name == "forward":
                self._check_clear_ahead()
            getattr(self.robot, name)(speed)
        elif name == "stop":
            self.robot.stop()
        elif self.config.camera_arm and name.startswith("camera_"):
            self._camera(name, float(args.get("step_deg", 10)))
        else:
            raise AdapterError(f"{name!r} is not a command of this car", code="unknown_command")

    def _check_clear_ahead(self) -> None:
        if self.sensor is None:
            return
        distance = self._read_distance()
        if distance is None:
            raise AdapterError(
                "the distance sensor has not given a reading: forward is refused",
                code="sensor_fault",
            )
        if distance < self.config.obstacle_stop_m:
            # Whole centimetres, rounded down so the message never reads "25 cm ahead
            # (stop distance 25 cm)".
            raise AdapterError(
                f"obstacle {math.floor(distance * 100)} cm ahead (stop distance "
                f"{self.config.obstacle_stop_m * 100:g} cm): forward is refused",
                code="obstacle",
            )

    def _camera(self, name: str, step: float) -> None:
        half = self.config.camera_range_deg / 2
        if name == "camera_center":
            self.pan_servo.angle = 0.0
            self.tilt_servo.angle = 0.0
            return
        servo, sign = {
            "camera_up": (self.tilt_servo, 1.0),
            "camera_down": (self.tilt_servo, -1.0),
            "camera_left": (self.pan_servo, -1.0),
            "camera_right": (self.pan_servo, 1.0),
        }.get(name, (None, 0.0))
        if servo is None:
            raise AdapterError(f"{name!r} is not a command of this car", code="unknown_command")
        current = servo.angle
        current = 0.0 if current is None else float(current)
        # Clamp at the ends of travel: pushing past them is a no-op, not an error.
        servo.angle = max(-half, min(half, current + sign * step))

    async def safe_action(self, action: str) -> None:
        """Stop: a car can neither land nor find its way home, so every action maps
        to ``stop``."""
        if action != "stop":
            logger.info("car: safe action %r carried out as stop", action)
        if self.robot is not None:
            self.robot.stop()

    async def neutral(self) -> None:
        """Stop the motors; the camera stays where it points."""
        if self.robot is not None:
            self.robot.stop()

    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where ``forward``/``backward`` at the requested speed put the car in 1 s;
        None for other commands or while the position is unknown."""
        if name not in ("forward", "backward"):
            return None
        position, heading = self._pose()
        if position is None or heading is None:
            return None
        distance = float(args.get("speed", 0.5)) * self.config.max_speed_mps
        if name == "backward":
            distance = -distance
        h = math.radians(heading)
        lat, lon = offset(position, distance * math.cos(h), distance * math.sin(h))
        return Projection(lat=lat, lon=lon)

    # --- the watch loop -----------------------------------------------------------------
    async def _watch(self) -> None:
        """Every 1/watch_hz s: read the distance sensor and stop the car if it is
        driving forwards into an obstacle; on a real car, dead-reckon the pose.

        Runs on the event loop, like execute(), so a stop here can never interleave
        half-way through a command. Errors are logged and the loop goes on: a dead
        watch would silently disable the obstacle stop.
        """
        period = 1.0 / self.config.watch_hz
        while True:
            try:
                self._watch_once()
            except Exception:
                logger.exception("car watch loop iteration failed")
            await asyncio.sleep(period)

    def _watch_once(self) -> None:
        motors = self._motor_values()
        if self.sensors is None:
            self._dead_reckon(motors)
        if self.sensor is None or motors is None:
            return
        distance = self._read_distance()
        # Forward component only: spinning on the spot or backing away from the
        # obstacle is what the user must still be able to do.
        near = distance is not None and distance < self.config.obstacle_stop_m
        if near and motors[0] + motors[1] > 0:
            self.robot.stop()
            self.obstacle_stops += 1
            logger.warning("car: obstacle %.2f m ahead, stopped", distance)

    def _dead_reckon(self, motors: tuple[float, float] | None) -> None:
        now = time.monotonic()
        last, self._odometry_t = self._odometry_t, now
        if last is None or motors is None:
            return
        v = self.config.max_speed_mps
        self._odometry = diff_drive_step(
            self._odometry,
            motors[0] * v,
            motors[1] * v,
            track_width_m=self.config.track_width_m,
            dt=min(now - last, 0.5),
        )
