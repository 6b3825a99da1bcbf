"""The car's gpiozero mock pins wired to the simulated world.

* :class:`MotorInputs` reads a motor driver's inputs back from the mock pins (PWM duty
  cycles and direction levels) as an effort in [-1, 1]: what moves the simulated car is
  exactly what gpiozero told the motor driver;
* an HC-SR04 on the front: :class:`RangingTriggerPin` answers each trigger pulse of
  gpiozero's ``DistanceSensor`` with an echo pulse ``2 * distance / 343.26`` s long on
  an :class:`EchoPin`, the distance ray-cast by the world at the moment of the ping (no
  echo, i.e. the sensor's 38 ms time-out pulse, past 4 m).

gpiozero reads the distance sensor in its own thread: the ranger runs there.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from gpiozero.pins.mock import (  # type: ignore[import-untyped, unused-ignore]
    MockPWMPin,
    MockTriggerPin,
)

from agents.vehicles.car.config import DualPinMotorWiring, MotorWiring

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


class MotorInputs:
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
