"""The Spektrum plane's simulator: a flight controller on the far end of a pty.

:func:`simulation` is the integration's simulator hook (see
:class:`~agents.vehicles.base.Simulation`): it opens a pty pair, puts a
:class:`~.simulator.SpektrumSimulator` on the master side (a thread of this process, or
``python -m agents sim spektrum`` in its own), and yields the adapter options with the
slave's path as ``port``: the adapter opens it as it opens a real UART. The simulator's
model shares the adapter's flight envelope (hover throttle, climb rates, transition) so
that projections and landings agree with it. Only :mod:`agents.simulation` and tests
import this; :func:`cli` is ``python -m agents sim spektrum``.

The simulator's parameters (the ``simulator`` option): ``process`` (true: in a process
of its own, so the timing it measures is not disturbed by the agent's threads; default
false, a thread) and any :class:`~.model.SimParams` field (``updraft_mps``,
``battery_pct``, ``stall_speed_mps``...). It starts at the adapter's ``origin`` (else
:data:`SIM_ORIGIN`).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
import tty
from collections.abc import AsyncIterator, Mapping
from pathlib import Path
from typing import Any

from agents.vehicles.base import Simulation
from agents.vehicles.kit import simulator_split
from agents.vehicles.spektrum.config import SpektrumConfig
from agents.vehicles.spektrum.sim.line import FdLink
from agents.vehicles.spektrum.sim.model import SimParams
from agents.vehicles.spektrum.sim.simulator import SpektrumSimulator, cli

__all__ = ["SIM_ORIGIN", "cli", "simulation"]

#: Where the simulated plane starts when the options give no ``origin`` (Leiria).
SIM_ORIGIN = (39.7436, -8.8071)

ROOT = Path(__file__).resolve().parents[4]


def model_params(config: SpektrumConfig, params: Mapping[str, Any]) -> SimParams:
    """The model's parameters: the envelope shared with the adapter's ``config``, then
    ``params`` (the ``simulator`` option, without ``process``). Raises ValueError naming
    a bad one."""
    try:
        return SimParams.from_mapping({**config.model_params(), **params})
    except ValueError as exc:
        raise ValueError(f"spektrum option simulator: {exc}") from None


@contextlib.asynccontextmanager
async def simulation(options: Mapping[str, Any]) -> AsyncIterator[Simulation]:
    """Start a simulated flight controller for ``options`` (see the module docstring);
    yields the adapter options that reach it (``port``, ``origin``) and, as
    ``simulator``, the :class:`SpektrumSimulator` (thread) or its process. Raises
    ValueError naming a bad option before anything starts."""
    adapter_options, params = simulator_split(options)
    config = SpektrumConfig.from_options(adapter_options)
    in_process = params.pop("process", False)
    if not isinstance(in_process, bool):
        raise ValueError("spektrum option simulator.process: expected true or false")
    model = model_params(config, params)
    origin = config.origin or SIM_ORIGIN
    master, slave = os.openpty()
    owned = [master, slave]
    simulator: SpektrumSimulator | None = None
    process: subprocess.Popen[bytes] | None = None
    try:
        # Raw at once: until pyserial configures the slave, the line discipline would
        # echo and translate bytes.
        tty.setraw(slave)
        path = os.ttyname(slave)
        if in_process:
            process = _spawn(master, config, params, origin)
            os.close(master)  # the child has its own copy
        else:
            simulator = SpektrumSimulator(
                FdLink(master),
                origin=origin,
                params=model,
                frame_period_ms=config.frame_period_ms,
                system=config.system,
            )
            simulator.start()
        owned.remove(master)  # the simulator (or the child) owns it now
        yield Simulation(
            options={**adapter_options, "port": path, "origin": list(origin)},
            simulator=process if process is not None else simulator,
        )
    finally:
        if simulator is not None:
            await asyncio.to_thread(simulator.close)
        if process is not None:
            process.terminate()
            try:
                await asyncio.to_thread(process.wait, 3.0)
            except subprocess.TimeoutExpired:
                process.kill()
                await asyncio.to_thread(process.wait)
        # The slave stays open while the simulator runs: with no slave open the master
        # reads EIO, which the simulator would see as a broken line.
        for fd in owned:
            with contextlib.suppress(OSError):
                os.close(fd)


def _spawn(
    master: int, config: SpektrumConfig, params: Mapping[str, Any], origin: tuple[float, float]
) -> subprocess.Popen[bytes]:
    """``python -m agents sim spektrum`` on the inherited pty master."""
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    args = [
        sys.executable, "-m", "agents", "sim", "spektrum",
        "--fd", str(master),
        "--origin", f"{origin[0]},{origin[1]}",
        "--period-ms", str(config.frame_period_ms),
        "--system", str(config.system),
        "--params", json.dumps({**config.model_params(), **params}),
        "--quiet",
    ]  # fmt: skip
    if config.pump_realtime:
        args.append("--realtime")
    return subprocess.Popen(
        args,
        pass_fds=(master,),
        stdin=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": path},
        cwd=ROOT,
    )
