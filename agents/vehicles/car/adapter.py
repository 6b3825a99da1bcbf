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

Off a Pi (``simulate``, or no GPIO found) the adapter builds exactly the same gpiozero
devices on mock pins of a per-car ``MockFactory``; a
:class:`~agents.vehicles.car.sim.world.CarWorld` reads the motor pins back to move the
car, feeds the distance sensor's echo pin, and supplies position, heading, speed and
battery. On a real car, which has no GPS, position and heading are dead-reckoned from
the motor commands when ``origin`` is configured (and unknown otherwise); the battery
level is unknown.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from typing import Any

# gpiozero ships no type hints ("unused-ignore": the project config may already
# ignore missing imports).
import gpiozero  # type: ignore[import-untyped, unused-ignore]
from gpiozero.pins.mock import (  # type: ignore[import-untyped, unused-ignore]
    MockFactory,
    MockPWMPin,
)

from agents.geo import offset
from agents.vehicles.base import (
    Adapter,
    AdapterError,
    CommandSpec,
    Projection,
    VehicleState,
)
from agents.vehicles.car.sim.world import (
    CarWorld,
    DualPinMotorWiring,
    MotorWiring,
    PhaseEnableMotorWiring,
    PinName,
    Pose,
    diff_drive_step,
    obstacles_from_spec,
)
from agents.vehicles.kit import OptionReader

logger = logging.getLogger(__name__)

#: Where a simulated car starts when the options give no ``origin``: an arbitrary
#: point (Leiria, Portugal).
SIM_ORIGIN = (39.7436, -8.8071)

#: gpiozero's own order of preference for real pin factories.
REAL_PIN_FACTORIES = ("lgpio", "rpigpio", "pigpio", "native")

#: Default BCM pins: the CamJam EduKit #3 robot layout (the paper does not give its
#: wiring), with the pan/tilt servos on GPIO12/13, the Pi's hardware-PWM pins.
DEFAULT_DUAL_PINS = {"left": (9, 10), "right": (7, 8)}
#: Pololu DRV8835 kit (gpiozero's PololuDRV8835Robot): (phase, enable) per motor.
DEFAULT_PHASE_ENABLE_PINS = {"left": (5, 12), "right": (6, 13)}

SPEED_ARG = {
    "speed": {
        "type": "number",
        "min": 0,
        "max": 1,
        "default": 0.5,
        "description": "fraction of full motor power",
    }
}
STEP_ARG = {"step_deg": {"type": "number", "min": 1, "max": 90, "default": 10, "unit": "deg"}}

#: Keys of the agent config's ``adapter_options`` that the agent itself reads.
AGENT_OPTIONS = frozenset({"vehicle_type", "attributes"})

TELEMETRY_TOPICS = [
    "battery_level",
    "location",
    "heading",
    "speed",
    "distance_ahead",
    "camera_pan",
    "camera_tilt",
    "motors",
]


# --------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------


def _pin(value: Any, what: str) -> PinName:
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError(f"car option {what}: a GPIO pin must be a number or a name")
    return value


def _pair(value: Any, what: str) -> tuple[PinName, PinName]:
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise ValueError(f"car option {what}: expected two pins")
    return (_pin(value[0], what), _pin(value[1], what))


def _number(options: Mapping[str, Any], key: str, default: float, *, low: float = 0.0) -> float:
    value = options.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"car option {key}: expected a number")
    if value <= low:
        raise ValueError(f"car option {key}: must be > {low:g}")
    return float(value)


def _flag(options: Mapping[str, Any], key: str) -> bool:
    # Strict: bool("false") is True, and a YAML/JSON slip must not fit an arm or a sensor.
    value = options.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"car option {key}: expected true or false")
    return value


@dataclass(frozen=True)
class CarConfig:
    """The adapter's options, checked. See ``docs/vehicles/car.md`` for each one."""

    simulate: bool | None = None
    pin_factory: str | None = None
    left: MotorWiring = field(
        default_factory=lambda: DualPinMotorWiring(*DEFAULT_DUAL_PINS["left"])
    )
    right: MotorWiring = field(
        default_factory=lambda: DualPinMotorWiring(*DEFAULT_DUAL_PINS["right"])
    )
    camera_arm: bool = False
    camera_pan_pin: PinName = 12
    camera_tilt_pin: PinName = 13
    camera_range_deg: float = 180.0
    camera_pan_reversed: bool = False
    camera_tilt_reversed: bool = False
    servo_min_pulse_s: float = 0.0005
    servo_max_pulse_s: float = 0.0025
    distance_sensor: bool = False
    distance_trigger_pin: PinName = 17
    distance_echo_pin: PinName = 18
    distance_max_m: float = 4.0
    distance_queue_len: int = 3
    obstacle_stop_m: float = 0.25
    watch_hz: float = 25.0
    max_speed_mps: float = 0.5
    track_width_m: float = 0.15
    origin: tuple[float, float] | None = None
    heading_deg: float = 0.0
    # simulation only
    body_radius_m: float = 0.12
    battery_pct: float = 100.0
    battery_drain_pct_per_s: float = 0.05
    sim_hz: float = 50.0
    obstacles: tuple[Any, ...] = field(default_factory=tuple)

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> CarConfig:
        """Check ``options``; raises ValueError naming the first bad one."""
        simulate = options.get("simulate")
        if simulate is not None and not isinstance(simulate, bool):
            raise ValueError("car option simulate: expected true, false or null")
        factory = options.get("pin_factory")
        if factory is not None and not isinstance(factory, str):
            raise ValueError("car option pin_factory: expected a gpiozero pin factory name")

        driver = options.get("motor_driver", "dual")
        left: MotorWiring
        right: MotorWiring
        if driver == "dual":
            lf, lb = _pair(options.get("left_motor_pins", DEFAULT_DUAL_PINS["left"]), "left")
            rf, rb = _pair(options.get("right_motor_pins", DEFAULT_DUAL_PINS["right"]), "right")
            le, re_ = options.get("left_enable_pin"), options.get("right_enable_pin")
            left = DualPinMotorWiring(lf, lb, None if le is None else _pin(le, "left_enable"))
            right = DualPinMotorWiring(rf, rb, None if re_ is None else _pin(re_, "right_enable"))
        elif driver == "phase_enable":
            left = PhaseEnableMotorWiring(
                *_pair(options.get("left_motor_pins", DEFAULT_PHASE_ENABLE_PINS["left"]), "left")
            )
            right = PhaseEnableMotorWiring(
                *_pair(options.get("right_motor_pins", DEFAULT_PHASE_ENABLE_PINS["right"]), "right")
            )
        else:
            raise ValueError("car option motor_driver: expected 'dual' or 'phase_enable'")

        origin = OptionReader("car", options).origin()

        queue_len = options.get("distance_queue_len", 3)
        if isinstance(queue_len, bool) or not isinstance(queue_len, int) or queue_len < 1:
            raise ValueError("car option distance_queue_len: expected an integer >= 1")
        watch_hz = _number(options, "watch_hz", 25.0)
        if watch_hz < 20:
            raise ValueError("car option watch_hz: the obstacle watch must run at >= 20 Hz")
        heading = options.get("heading_deg", 0.0)
        if isinstance(heading, bool) or not isinstance(heading, int | float):
            raise ValueError("car option heading_deg: expected a number")
        battery = _number(options, "battery_pct", 100.0, low=-1e-9)
        if battery > 100:
            raise ValueError("car option battery_pct: at most 100")
        min_pulse = _number(options, "servo_min_pulse_s", 0.0005)
        max_pulse = _number(options, "servo_max_pulse_s", 0.0025)
        if not min_pulse < max_pulse < 0.02:
            raise ValueError("car options servo_*_pulse_s: need min < max < 20 ms")
        camera_range = _number(options, "camera_range_deg", 180.0)
        if camera_range > 360:
            raise ValueError("car option camera_range_deg: at most 360")
        obstacles = options.get("obstacles", ())
        obstacles_from_spec(obstacles)  # validate now; built when the world is

        config = cls(
            simulate=simulate,
            pin_factory=factory,
            left=left,
            right=right,
            camera_arm=_flag(options, "camera_arm"),
            camera_pan_pin=_pin(options.get("camera_pan_pin", 12), "camera_pan_pin"),
            camera_tilt_pin=_pin(options.get("camera_tilt_pin", 13), "camera_tilt_pin"),
            camera_range_deg=camera_range,
            camera_pan_reversed=_flag(options, "camera_pan_reversed"),
            camera_tilt_reversed=_flag(options, "camera_tilt_reversed"),
            servo_min_pulse_s=min_pulse,
            servo_max_pulse_s=max_pulse,
            distance_sensor=_flag(options, "distance_sensor"),
            distance_trigger_pin=_pin(options.get("distance_trigger_pin", 17), "trigger"),
            distance_echo_pin=_pin(options.get("distance_echo_pin", 18), "echo"),
            distance_max_m=_number(options, "distance_max_m", 4.0),
            distance_queue_len=queue_len,
            obstacle_stop_m=_number(options, "obstacle_stop_m", 0.25),
            watch_hz=watch_hz,
            max_speed_mps=_number(options, "max_speed_mps", 0.5),
            track_width_m=_number(options, "track_width_m", 0.15),
            origin=origin,
            heading_deg=float(heading),
            body_radius_m=_number(options, "body_radius_m", 0.12),
            battery_pct=battery,
            battery_drain_pct_per_s=_number(options, "battery_drain_pct_per_s", 0.05, low=-1e-9),
            sim_hz=_number(options, "sim_hz", 50.0, low=-1e-9),
            obstacles=tuple(obstacles),
        )
        config._check_pin_conflicts()
        unknown = set(options) - KNOWN_OPTIONS - AGENT_OPTIONS
        if unknown:
            # Warn rather than refuse (the options object is shared with the agent), but
            # loudly: a misspelt "distance_sensor" silently disables the obstacle stop.
            logger.warning("car: unknown options ignored: %s", ", ".join(sorted(unknown)))
        return config

    def _check_pin_conflicts(self) -> None:
        # gpiozero would refuse too, but only at start() and naming its own devices.
        used: dict[str, str] = {}

        def claim(pin: PinName | None, role: str) -> None:
            if pin is None:
                return
            key = str(pin).upper().removeprefix("GPIO")
            if key in used:
                raise ValueError(f"car options: pin {pin} is both {used[key]} and {role}")
            used[key] = role

        for side, wiring in (("left", self.left), ("right", self.right)):
            if isinstance(wiring, DualPinMotorWiring):
                claim(wiring.forward, f"{side} motor forward")
                claim(wiring.backward, f"{side} motor backward")
                claim(wiring.enable, f"{side} motor enable")
            else:
                claim(wiring.phase, f"{side} motor phase")
                claim(wiring.enable, f"{side} motor enable")
        if self.camera_arm:
            claim(self.camera_pan_pin, "camera pan servo")
            claim(self.camera_tilt_pin, "camera tilt servo")
        if self.distance_sensor:
            claim(self.distance_trigger_pin, "distance sensor trigger")
            claim(self.distance_echo_pin, "distance sensor echo")


#: Every option :meth:`CarConfig.from_options` reads.
KNOWN_OPTIONS = frozenset(
    {
        "simulate",
        "pin_factory",
        "motor_driver",
        "left_motor_pins",
        "right_motor_pins",
        "left_enable_pin",
        "right_enable_pin",
        "camera_arm",
        "camera_pan_pin",
        "camera_tilt_pin",
        "camera_range_deg",
        "camera_pan_reversed",
        "camera_tilt_reversed",
        "servo_min_pulse_s",
        "servo_max_pulse_s",
        "distance_sensor",
        "distance_trigger_pin",
        "distance_echo_pin",
        "distance_max_m",
        "distance_queue_len",
        "obstacle_stop_m",
        "watch_hz",
        "max_speed_mps",
        "track_width_m",
        "origin",
        "heading_deg",
        "body_radius_m",
        "battery_pct",
        "battery_drain_pct_per_s",
        "sim_hz",
        "obstacles",
    }
)


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
    watch and, when simulating, the world.

    Public attributes for diagnostics and tests, None until started or when absent:
    ``robot``, ``pan_servo``, ``tilt_servo``, ``sensor`` (the gpiozero devices),
    ``pin_factory``, ``world`` (simulation only) and ``simulated``.
    """

    name = "car"

    def __init__(self, options: Mapping[str, Any]) -> None:
        super().__init__(options)
        self.config = CarConfig.from_options(options)
        self.simulated = False
        self.pin_factory: Any = None
        self.world: CarWorld | None = None
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
        """Open the devices, wait (up to 2 s) for the first distance reading, start the
        watch loop and, when simulating, the world. Raises AdapterError ``hardware``
        when there is no GPIO and ``simulate`` is false, or a device cannot be opened."""
        if self.robot is not None:
            return
        cfg = self.config
        factory: Any
        if cfg.simulate:
            factory = None
        else:
            try:
                factory = _load_pin_factory(cfg.pin_factory)
            except RuntimeError as exc:
                if cfg.simulate is False:
                    raise AdapterError(f"no usable GPIO: {exc}", code="hardware") from None
                logger.warning("no GPIO on this machine (%s): simulating the car", exc)
                factory = None
        if factory is None:
            self.simulated = True
            # One factory per car: its pins and reservations are its own, so several
            # simulated cars can share a process (gpiozero's global factory is untouched).
            factory = MockFactory(pin_class=MockPWMPin)
            self.world = CarWorld(
                factory,
                left=cfg.left,
                right=cfg.right,
                origin=cfg.origin or SIM_ORIGIN,
                pose=Pose(heading_deg=cfg.heading_deg),
                max_speed_mps=cfg.max_speed_mps,
                track_width_m=cfg.track_width_m,
                body_radius_m=cfg.body_radius_m,
                battery_pct=cfg.battery_pct,
                battery_drain_pct_per_s=cfg.battery_drain_pct_per_s,
                sensor_max_range_m=cfg.distance_max_m,
                obstacles=obstacles_from_spec(cfg.obstacles),
            )
            if cfg.distance_sensor:
                self.world.attach_distance_sensor(cfg.distance_trigger_pin, cfg.distance_echo_pin)
        else:
            self._own_factory = True
        self.pin_factory = factory

        try:
            self._open_devices(factory)
        except Exception as exc:
            await self.close()
            raise AdapterError(
                f"cannot open the car's GPIO devices: {exc}", code="hardware"
            ) from exc

        if self.world is not None and cfg.sim_hz > 0:
            # sim_hz 0: nothing steps the world but the caller (deterministic tests).
            self._tasks.append(asyncio.create_task(self.world.run(cfg.sim_hz), name="car-world"))
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
                if self.simulated:
                    # Advice to use pigpio for accurate timing: moot on mock pins.
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
        out = [
            CommandSpec(
                "forward",
                "Drive forwards (refused when an obstacle is close ahead)",
                group="movement",
                args=SPEED_ARG,
                motion=True,
                speed_arg="speed",
                key="ArrowUp",
            ),
            CommandSpec(
                "backward",
                "Drive backwards",
                group="movement",
                args=SPEED_ARG,
                motion=True,
                speed_arg="speed",
                key="ArrowDown",
            ),
            CommandSpec(
                "left",
                "Turn left on the spot",
                group="movement",
                args=SPEED_ARG,
                motion=True,
                speed_arg="speed",
                key="ArrowLeft",
            ),
            CommandSpec(
                "right",
                "Turn right on the spot",
                group="movement",
                args=SPEED_ARG,
                motion=True,
                speed_arg="speed",
                key="ArrowRight",
            ),
            # Not a motion command: it moves nothing, and must pass every limit anyway.
            CommandSpec("stop", "Stop the motors", group="movement", key="Space"),
        ]
        if self.config.camera_arm:
            for name, text, key in (
                ("camera_up", "Tilt the camera up", "w"),
                ("camera_down", "Tilt the camera down", "s"),
                ("camera_left", "Pan the camera left", "a"),
                ("camera_right", "Pan the camera right", "d"),
            ):
                out.append(CommandSpec(name, text, group="camera", args=STEP_ARG, key=key))
            out.append(CommandSpec("camera_center", "Centre the camera", group="camera", key="c"))
        return out

    def telemetry_topics(self) -> list[str]:
        return list(TELEMETRY_TOPICS)

    # --- reading ----------------------------------------------------------------------
    def _motor_values(self) -> tuple[float, float] | None:
        if self.robot is None:
            return None
        left, right = self.robot.value
        return (float(left), float(right))

    def _pose(self) -> tuple[tuple[float, float] | None, float | None]:
        """((lat, lon) or None, heading or None) from the world or dead reckoning."""
        if self.world is not None:
            return self.world.position, self.world.heading_deg
        if self.config.origin is None:
            return None, None
        pose = self._odometry
        return offset(self.config.origin, pose.north_m, pose.east_m), pose.heading_deg

    def _speed_mps(self) -> float | None:
        if self.world is not None:
            return self.world.speed_mps
        values = self._motor_values()
        if values is None:
            return None
        return abs(values[0] + values[1]) / 2 * self.config.max_speed_mps

    def state(self) -> VehicleState:
        """Position and heading (simulated, or dead-reckoned from ``origin``; None when
        unknown), ground speed, and battery (simulation only)."""
        position, heading = self._pose()
        return VehicleState(
            lat=None if position is None else position[0],
            lon=None if position is None else position[1],
            heading_deg=heading,
            speed_mps=self._speed_mps(),
            battery=None if self.world is None else self.world.battery_pct,
        )

    def telemetry(self) -> dict[str, Any]:
        """Every topic of :data:`TELEMETRY_TOPICS`; None where unknown or absent."""
        position, heading = self._pose()
        speed = self._speed_mps()
        motors = self._motor_values()
        return {
            "battery_level": None if self.world is None else round(self.world.battery_pct, 2),
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
            speed = min(1.0, max(0.0, float(args.get("speed", 0.5))))
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
        if self.world is None:
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
