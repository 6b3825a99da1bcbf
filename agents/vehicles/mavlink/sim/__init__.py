"""The MAVLink simulator: an ArduPilot-like autopilot in a process of its own, playing
an ArduCopter quadcopter or an ArduRover boat (the adapter options' ``vehicle_class``).

Files: ``autopilot`` (the wire: heartbeats, streams, parameters, commands, the GCS
fail-safe's clock), ``messages`` (the telemetry it sends), ``vehicle`` (what every
simulated vehicle shares), ``copter`` and ``boat`` (their modes and kinematics),
``params`` (each firmware's parameters), ``cli`` (``python -m agents sim mavlink``).

:func:`simulation` is the integration's simulator hook (see
:class:`~agents.vehicles.base.Simulation`): it starts ``python -m agents sim mavlink``
listening on a free UDP port of the loopback, waits for it to say ``READY``, and yields
the adapter options with ``connection`` pointing there; the process (a
``subprocess.Popen``) is the ``simulator``, and it stops when the block ends (or when
its parent process dies). Only :mod:`agents.simulation` and tests import this.

The simulator's parameters (the ``simulator`` option) are its command line's:

``speedup``, ``battery_pct``, ``drain_pct_per_min``, ``gps`` (3d, 2d, none),
``satellites``, ``heading_deg``, ``home_alt_m``, ``sysid``, ``params`` ({NAME:
number}, names of the simulated firmware), ``gps_fix_after_s``, ``firmware`` (4.5,
4.7), ``stream_rate_hz``, and a boat's ``current_mps`` and ``current_towards_deg``; it
starts at the adapter's ``origin`` (else :data:`SIM_ORIGIN`, or :data:`BOAT_SIM_ORIGIN`
for a boat).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

from agents.vehicles.base import Simulation
from agents.vehicles.kit import OptionReader, simulator_split
from agents.vehicles.mavlink.classes import VEHICLE_CLASSES
from agents.vehicles.mavlink.config import MavlinkConfig
from agents.vehicles.mavlink.sim.autopilot import VEHICLES
from agents.vehicles.mavlink.sim.cli import cli
from agents.vehicles.mavlink.sim.params import DEFAULT_FIRMWARE, FIRMWARES, firmware_params

__all__ = ["BOAT_SIM_ORIGIN", "SIM_ORIGIN", "cli", "simulation", "simulator_command"]

#: Where a simulated copter starts when the options give no ``origin`` (the campus).
SIM_ORIGIN = (40.6306, -8.6588)
#: ... and a boat: at sea off Barra beach, west of the demo's Costa Nova station.
BOAT_SIM_ORIGIN = (40.6443, -8.7540)
#: Parameters a simulated autopilot starts with unless ``simulator.params`` says
#: otherwise: what an operator would set on a real one. The copter: the agent's
#: heartbeat loss -> its GCS fail-safe (RTL). The boat: the same, FS_ACTION RTL (else
#: Hold), and (see :func:`simulation`) WP_SPEED at the adapter's ``max_speed_mps``,
#: without which ArduRover caps every speed at its 2 m/s default.
SIM_DEFAULT_PARAMS: Mapping[str, Mapping[str, float]] = {
    "copter": {"FS_GCS_ENABLE": 1.0},
    "boat": {"FS_GCS_ENABLE": 1.0, "FS_ACTION": 1.0},
}
#: The simulator's command line flag for each parameter.
FLAGS = {
    "speedup": "--speedup",
    "battery_pct": "--battery",
    "drain_pct_per_min": "--drain",
    "gps": "--gps",
    "satellites": "--satellites",
    "heading_deg": "--heading",
    "home_alt_m": "--home-alt",
    "sysid": "--sysid",
    "gps_fix_after_s": "--gps-fix-after",
    "firmware": "--firmware",
    "stream_rate_hz": "--stream-rate",
}
#: How long the simulator may take to say READY (a loaded machine imports slowly).
READY_WITHIN_S = 30.0

ROOT = Path(__file__).resolve().parents[4]


def simulator_command(
    params: Mapping[str, Any],
    *,
    home: tuple[float, float],
    vehicle_class: str = "copter",
    defaults: Mapping[str, float] | None = None,
) -> list[str]:
    """The command line of a simulated ``vehicle_class`` with ``params`` (the
    ``simulator`` option), listening on a free loopback port; ``defaults`` are
    autopilot parameters it starts with unless ``params["params"]`` says otherwise.
    Raises ValueError naming a bad parameter (or a class the simulator does not play).

    Unless ``params`` say otherwise it ships no telemetry until the agent asks for it,
    as ArduCopter does (stream rate 0), so that the agent's own stream requests are
    what the tests fly on."""
    if vehicle_class not in VEHICLES:
        raise ValueError(
            f"mavlink option vehicle_class: the simulator plays a {' or a '.join(VEHICLES)}, "
            f"not a {vehicle_class}"
        )
    o = OptionReader("mavlink", params, prefix="simulator.")
    args = [
        sys.executable, "-m", "agents", "sim", "mavlink",
        "--listen", "udpin:127.0.0.1:0",
        "--vehicle-class", vehicle_class,
        "--home", f"{home[0]},{home[1]}",
        "--parent-pid", str(os.getpid()),
    ]  # fmt: skip
    values: dict[str, Any] = {"stream_rate_hz": 0}
    for key in ("speedup", "battery_pct", "drain_pct_per_min", "heading_deg", "home_alt_m"):
        if o.has(key):
            values[key] = o.number(key, 0)
    for key in ("gps_fix_after_s", "stream_rate_hz"):
        if o.has(key):
            values[key] = o.number(key, 0, min=0)
    for key in ("satellites", "sysid"):
        if o.has(key):
            values[key] = o.integer(key, 0, min=0, max=255)
    if o.has("gps"):
        values["gps"] = o.choice("gps", "3d", ("3d", "2d", "none"))
    if o.has("firmware"):
        values["firmware"] = o.choice("firmware", DEFAULT_FIRMWARE, FIRMWARES)
    if vehicle_class == "boat":
        speed = o.number("current_mps", 0.0, min=0, max=5)
        towards = o.number("current_towards_deg", 0.0, min=0, max=360)
        if speed:
            args += ["--current", f"{speed},{towards}"]
    extra = o.mapping("params")
    if not all(
        isinstance(k, str) and isinstance(v, int | float) and not isinstance(v, bool)
        for k, v in extra.items()
    ):
        raise o.error("params", "expected {NAME: number}")
    firmware = values.get("firmware", DEFAULT_FIRMWARE)
    unknown = sorted(set(extra) - set(firmware_params(firmware, vehicle_class)))
    if unknown:
        name = VEHICLE_CLASSES[vehicle_class].firmware
        raise o.error("params", f"{name} {firmware} has no parameter {', '.join(unknown)}")
    o.finish()
    for key, value in values.items():
        args += [FLAGS[key], str(value)]
    start = {**SIM_DEFAULT_PARAMS[vehicle_class], **(defaults or {}), **extra}
    for name, value in start.items():
        args += ["--param", f"{name}={value}"]
    return args


@contextlib.asynccontextmanager
async def simulation(options: Mapping[str, Any]) -> AsyncIterator[Simulation]:
    """Start a simulated autopilot for ``options`` (see the module docstring); yields
    the adapter options that connect to it. Raises ValueError naming a bad option, or
    RuntimeError when the simulator does not come up."""
    adapter_options, params = simulator_split(options)
    config = MavlinkConfig.from_options(adapter_options)
    vehicle_class = config.vehicle_class.name
    boat = vehicle_class == "boat"
    args = simulator_command(
        params,
        home=config.origin or (BOAT_SIM_ORIGIN if boat else SIM_ORIGIN),
        vehicle_class=vehicle_class,
        defaults={"WP_SPEED": config.max_speed_mps} if boat else None,
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p),
    }

    def spawn() -> subprocess.Popen[bytes]:
        return subprocess.Popen(
            args, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, env=env, cwd=ROOT
        )

    process = await asyncio.to_thread(spawn)
    try:
        port = await _ready_port(process)
        yield Simulation(
            options={
                **adapter_options,
                "connection": f"udpout:127.0.0.1:{port}",
                # A simulated vehicle is left where it is when its agent stops, as
                # before the simulator hook existed; a config may still ask otherwise.
                "close_action": adapter_options.get("close_action", "none"),
            },
            simulator=process,
        )
    finally:
        if process.poll() is None:
            process.terminate()
            try:
                await asyncio.to_thread(process.wait, 5.0)
            except subprocess.TimeoutExpired:
                process.kill()
                await asyncio.to_thread(process.wait)
        if process.stdout is not None:
            process.stdout.close()


async def _ready_port(process: subprocess.Popen[bytes]) -> int:
    """The UDP port of ``READY udpin:127.0.0.1:PORT``, the simulator's first line."""
    assert process.stdout is not None
    try:
        async with asyncio.timeout(READY_WITHIN_S):
            line = await asyncio.to_thread(process.stdout.readline)
    except TimeoutError:
        process.kill()  # ends the blocked read too
        raise RuntimeError(f"the MAVLink simulator did not start in {READY_WITHIN_S:g} s") from None
    text = line.decode(errors="replace").strip()
    if not text.startswith("READY "):
        code = process.wait()
        raise RuntimeError(f"the MAVLink simulator exited with code {code}: {text!r}")
    return int(text.rsplit(":", 1)[1])
