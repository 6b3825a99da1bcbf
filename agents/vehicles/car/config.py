"""The car's options (``adapter_options``), checked: wiring, devices, speeds.

Read with the kit's :class:`~agents.vehicles.kit.OptionReader` (unknown keys refused);
every option is described in ``docs/vehicles/car.md``. No hardware library is imported
here: the platform reads the car's vocabulary from a config without gpiozero.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeAlias

from agents.vehicles.kit import OptionReader

#: A GPIO pin as gpiozero names it: a BCM number (17) or a name ("GPIO17", "BOARD11").
PinName: TypeAlias = int | str

#: Default BCM pins: the CamJam EduKit #3 robot layout (the paper does not give its
#: wiring), with the pan/tilt servos on GPIO12/13, the Pi's hardware-PWM pins.
DEFAULT_DUAL_PINS = {"left": (9, 10), "right": (7, 8)}
#: Pololu DRV8835 kit (gpiozero's PololuDRV8835Robot): (phase, enable) per motor.
DEFAULT_PHASE_ENABLE_PINS = {"left": (5, 12), "right": (6, 13)}


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


class CarSensors(Protocol):
    """Something that knows where the car is better than dead reckoning from the motor
    commands: the simulated world (its simulator hands it over as the ``sensors``
    option), or a GPS and battery monitor of a car's own. Read on the event loop; must
    not block. ``battery_pct`` may be None when there is no battery monitor."""

    @property
    def position(self) -> tuple[float, float]: ...

    @property
    def heading_deg(self) -> float: ...

    @property
    def speed_mps(self) -> float: ...

    @property
    def battery_pct(self) -> float | None: ...


def _pin(reader: OptionReader, key: str, value: Any) -> PinName:
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise reader.error(key, "a GPIO pin must be a number or a name")
    return value


def _pair(reader: OptionReader, key: str, default: tuple[int, int]) -> tuple[PinName, PinName]:
    value = reader.get(key, default)
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise reader.error(key, "expected two pins")
    return (_pin(reader, key, value[0]), _pin(reader, key, value[1]))


@dataclass(frozen=True)
class CarConfig:
    """The adapter's options, checked. See ``docs/vehicles/car.md`` for each one.

    ``pin_factory`` is a gpiozero pin factory's name (None: the first real one that
    loads), or a factory object (the simulator's mock pins). ``sensors`` is a
    :class:`CarSensors` or None (position dead-reckoned from ``origin``).
    """

    pin_factory: Any = None
    sensors: CarSensors | None = None
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
    #: How fast a held turn key spins the car on the spot: slow enough to aim it.
    turn_rate_deg_s: float = 45.0
    origin: tuple[float, float] | None = None
    heading_deg: float = 0.0

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> CarConfig:
        """Check ``options``; raises ValueError naming the first bad one (or every
        unknown key)."""
        o = OptionReader("car", options)
        factory = o.get("pin_factory")
        if factory is not None and not isinstance(factory, str) and not hasattr(factory, "pin"):
            raise o.error("pin_factory", "expected a gpiozero pin factory name")
        sensors = o.get("sensors")
        if sensors is not None and not all(
            hasattr(sensors, name) for name in ("position", "heading_deg", "speed_mps")
        ):
            raise o.error("sensors", "expected an object giving position, heading and speed")

        driver = o.choice("motor_driver", "dual", ("dual", "phase_enable"))
        left: MotorWiring
        right: MotorWiring
        if driver == "dual":
            lf, lb = _pair(o, "left_motor_pins", DEFAULT_DUAL_PINS["left"])
            rf, rb = _pair(o, "right_motor_pins", DEFAULT_DUAL_PINS["right"])
            le, re_ = o.get("left_enable_pin"), o.get("right_enable_pin")
            left = DualPinMotorWiring(
                lf, lb, None if le is None else _pin(o, "left_enable_pin", le)
            )
            right = DualPinMotorWiring(
                rf, rb, None if re_ is None else _pin(o, "right_enable_pin", re_)
            )
        else:
            left = PhaseEnableMotorWiring(
                *_pair(o, "left_motor_pins", DEFAULT_PHASE_ENABLE_PINS["left"])
            )
            right = PhaseEnableMotorWiring(
                *_pair(o, "right_motor_pins", DEFAULT_PHASE_ENABLE_PINS["right"])
            )

        watch_hz = o.number("watch_hz", 25.0, above=0)
        if watch_hz < 20:
            raise o.error("watch_hz", "the obstacle watch must run at >= 20 Hz")
        min_pulse = o.number("servo_min_pulse_s", 0.0005, above=0)
        max_pulse = o.number("servo_max_pulse_s", 0.0025, above=0)
        if not min_pulse < max_pulse < 0.02:
            raise ValueError("car options servo_*_pulse_s: need min < max < 20 ms")

        config = cls(
            pin_factory=factory,
            sensors=sensors,
            left=left,
            right=right,
            camera_arm=o.flag("camera_arm"),
            camera_pan_pin=_pin(o, "camera_pan_pin", o.get("camera_pan_pin", 12)),
            camera_tilt_pin=_pin(o, "camera_tilt_pin", o.get("camera_tilt_pin", 13)),
            camera_range_deg=o.number("camera_range_deg", 180.0, above=0, max=360),
            camera_pan_reversed=o.flag("camera_pan_reversed"),
            camera_tilt_reversed=o.flag("camera_tilt_reversed"),
            servo_min_pulse_s=min_pulse,
            servo_max_pulse_s=max_pulse,
            distance_sensor=o.flag("distance_sensor"),
            distance_trigger_pin=_pin(o, "distance_trigger_pin", o.get("distance_trigger_pin", 17)),
            distance_echo_pin=_pin(o, "distance_echo_pin", o.get("distance_echo_pin", 18)),
            distance_max_m=o.number("distance_max_m", 4.0, above=0),
            distance_queue_len=o.integer("distance_queue_len", 3, min=1),
            obstacle_stop_m=o.number("obstacle_stop_m", 0.25, above=0),
            watch_hz=watch_hz,
            max_speed_mps=o.number("max_speed_mps", 0.5, above=0),
            track_width_m=o.number("track_width_m", 0.15, above=0),
            turn_rate_deg_s=o.number("turn_rate_deg_s", 45.0, above=0, max=720),
            origin=o.origin(),
            heading_deg=o.number("heading_deg", 0.0),
        )
        o.finish()
        config._check_pin_conflicts()
        return config

    @property
    def turn_power(self) -> float:
        """The motor power (a fraction of full) that spins the car on the spot at
        :attr:`turn_rate_deg_s`: each wheel at the rate times half the track."""
        wheel_mps = math.radians(self.turn_rate_deg_s) * self.track_width_m / 2
        return round(min(1.0, max(0.01, wheel_mps / self.max_speed_mps)), 3)

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
