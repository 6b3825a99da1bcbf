"""How a MAVLink vehicle brakes: its autopilot's acceleration and jerk limits.

The agent's gate predicts where a held movement comes to rest (:mod:`agents.safety`);
for that it needs what the autopilot brakes with. ArduCopter's GUIDED velocity control
shapes every setpoint within ``WPNAV_ACCEL`` (horizontal, cm/s²) and ``WPNAV_ACCEL_Z``
(vertical), ramping the acceleration at ``PSC_JERK_XY`` / ``PSC_JERK_Z`` (m/s³; renamed
``PSC_JERK_NE`` / ``PSC_JERK_D`` in ArduPilot 4.7). ArduRover's speed controller brakes
at ``ATC_DECEL_MAX`` (m/s², 0: ``ATC_ACCEL_MAX``), with no jerk limit.

:func:`kinematics_read` reads them once the autopilot answers (the newer name first);
until then, and for a parameter that never answers, the firmware's defaults stand. The
adapter options ``decel_mps2`` (and a copter's ``decel_z_mps2``) override what is read,
for an autopilot whose limits the agent must not trust or cannot read.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from dataclasses import dataclass

from agents.vehicles.base import AdapterError, Stopping
from agents.vehicles.mavlink.classes import VehicleClass
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.link import AutopilotLink

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class AxisLimits:
    """One axis's braking: its deceleration (m/s²) and the jerk (m/s³) the autopilot
    ramps up to it with (None: at once)."""

    decel_mps2: float
    jerk_mps3: float | None = None

    def stopping(self, reaction_s: float) -> Stopping:
        """The axis as the gate predicts it, after ``reaction_s`` of the agent's own
        (the setpoint's hold, the position's age); the ramp up to full braking counts
        as half its time at full speed."""
        ramp = 0.0 if not self.jerk_mps3 else self.decel_mps2 / (2.0 * self.jerk_mps3)
        return Stopping(decel_mps2=self.decel_mps2, reaction_s=reaction_s + ramp)


@dataclass(frozen=True)
class Kinematics:
    """How the vehicle brakes horizontally and (a copter) vertically; ``source`` says
    where the figures come from (``defaults``, ``autopilot``, ``options``)."""

    horizontal: AxisLimits
    vertical: AxisLimits | None
    source: str = "defaults"


#: One figure: the autopilot's names for it (newest first), the factor from its units
#: to SI, and the firmware's default (in SI).
_Figure = tuple[Sequence[str], float, float]
COPTER_FIGURES: dict[str, _Figure] = {
    "decel": (("WPNAV_ACCEL",), 0.01, 2.5),
    "jerk": (("PSC_JERK_NE", "PSC_JERK_XY"), 1.0, 5.0),
    "decel_z": (("WPNAV_ACCEL_Z",), 0.01, 1.0),
    "jerk_z": (("PSC_JERK_D", "PSC_JERK_Z"), 1.0, 5.0),
}
ROVER_FIGURES: dict[str, _Figure] = {
    "decel": (("ATC_DECEL_MAX",), 1.0, 0.0),
    "accel": (("ATC_ACCEL_MAX",), 1.0, 1.0),
}
#: ArduRover's ATC_ACCEL_MAX 0 means no limit; a boat still needs time to stop.
ROVER_UNLIMITED_DECEL_MPS2 = 2.0


def kinematics_default(vehicle_class: VehicleClass, config: MavlinkConfig) -> Kinematics:
    """The firmware's defaults, with what the options declare."""
    return _kinematics(vehicle_class, config, {}, "defaults")


async def kinematics_read(
    link: AutopilotLink, vehicle_class: VehicleClass, config: MavlinkConfig
) -> Kinematics:
    """The limits the autopilot has (all read at once; a name it does not answer for
    keeps the default), with what the options declare. Never raises."""
    figures = COPTER_FIGURES if vehicle_class.flies else ROVER_FIGURES
    names = [name for names, _, _ in figures.values() for name in names]
    answers = await asyncio.gather(
        *(link.read_param(name) for name in names), return_exceptions=True
    )
    values: dict[str, float] = {}
    for name, answer in zip(names, answers, strict=True):
        if isinstance(answer, float):
            values[name] = answer
        elif not isinstance(answer, AdapterError):
            logger.warning("mavlink: reading %s failed: %r", name, answer)
    found: dict[str, float] = {}
    for key, (alternatives, scale, _) in figures.items():
        value = next((values[n] for n in alternatives if n in values), None)
        if value is not None:
            found[key] = value * scale
    kinematics = _kinematics(vehicle_class, config, found, "autopilot" if found else "defaults")
    logger.info("mavlink: the vehicle brakes %s", kinematics)
    return kinematics


def _kinematics(
    vehicle_class: VehicleClass, config: MavlinkConfig, found: dict[str, float], source: str
) -> Kinematics:
    figures = COPTER_FIGURES if vehicle_class.flies else ROVER_FIGURES
    v = {key: found.get(key, default) for key, (_, _, default) in figures.items()}
    if config.decel_mps2 is not None or config.decel_z_mps2 is not None:
        source = "options"
    if vehicle_class.flies:
        horizontal = AxisLimits(config.decel_mps2 or v["decel"], v["jerk"] or None)
        vertical = AxisLimits(config.decel_z_mps2 or v["decel_z"], v["jerk_z"] or None)
        return Kinematics(horizontal, vertical, source)
    decel = v["decel"] or v["accel"] or ROVER_UNLIMITED_DECEL_MPS2
    return Kinematics(AxisLimits(config.decel_mps2 or decel), None, source)
