"""The abstraction layer: one adapter interface for every kind of vehicle.

The agent talks to a vehicle only through an :class:`Adapter`. An adapter declares its
command vocabulary (:class:`CommandSpec`) and telemetry topics, executes commands the
agent has already checked against the task, reports the vehicle's state and performs
the safe action on a fail-safe. Users and service developers never see MAVLink, GPIO or
serial frames.

Each vehicle integration is one folder under ``agents/vehicles/`` (its adapter, its
options, its wire format and its simulator), declared to the registry
(:mod:`agents.vehicles.registry`); ``docs/integrating-a-vehicle.md`` walks through one.
What every adapter shares is here and in :mod:`agents.vehicles.kit` (the option reader):

* the abstract methods every adapter implements, and the optional hooks with their
  defaults (:meth:`Adapter.neutral`, :meth:`Adapter.envelope_recover`,
  :meth:`Adapter.project`, :meth:`Adapter.braking`, :meth:`Adapter.stop_motion`,
  :meth:`Adapter.check_failsafe_params`, :meth:`Adapter.fence_set` and
  :meth:`Adapter.fence_clear`, :meth:`Adapter.native_missions` (an autopilot's own
  mission engine, :mod:`agents.vehicles.plan`), the event sink
  :attr:`Adapter.on_event` with :meth:`Adapter.emit`, :meth:`Adapter.video_source`);
* the simulator hook's contract (:class:`Simulation`): an integration's simulator
  module offers ``simulation(options)``, an async context manager that starts the
  simulator and yields the adapter options that drive the simulated vehicle. Only the
  simulation runner (:mod:`agents.simulation`) and tests call it: production code never
  imports a simulator.

Lifecycle: ``async with adapter_create(name, options) as adapter: ...`` calls
:meth:`Adapter.start` and, whatever happens, :meth:`Adapter.close`.
"""

from __future__ import annotations

import abc
import logging
import math
from collections.abc import Callable, Mapping
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, ClassVar, Self

from agents.telemetry import TopicInfo, topics_info
from agents.vehicles.plan import NativeMissions

logger = logging.getLogger(__name__)

#: Commands that make a vehicle safer; they pass every latency limit.
SAFE_COMMANDS = frozenset({"stop", "land", "return_to_home"})


class AdapterError(Exception):
    """The vehicle refused or could not carry out a command.

    ``code`` is a short machine-readable reason ("obstacle", "not_armed", "timeout",
    "autopilot_refused", ...); ``str(exc)`` is the sentence shown to the user.
    """

    def __init__(self, message: str, *, code: str = "refused") -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class CommandSpec:
    """One command of a vehicle's vocabulary, as reported in its profile.

    ``args`` maps argument name to the protocol's arg spec (``type``, ``min``, ``max``,
    ``default``, ``unit``). ``motion`` commands move the vehicle: the client repeats
    them while a key is held and they are refused past the hard latency limit.
    ``speed_arg`` names the argument the agent lowers as latency grows.
    """

    name: str
    description: str = ""
    group: str = ""
    args: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    motion: bool = False
    speed_arg: str | None = None
    key: str | None = None  # default key binding for controllers, e.g. "ArrowUp"

    def to_profile(self) -> dict[str, Any]:
        """The JSON form sent in the agent's profile and to controllers."""
        out: dict[str, Any] = {
            "name": self.name,
            "args": {k: dict(v) for k, v in self.args.items()},
            "description": self.description,
            "group": self.group,
            "motion": self.motion,
        }
        if self.key:
            out["key"] = self.key
        return out


@dataclass(frozen=True)
class VehicleState:
    """What the agent knows of the vehicle now; None where the vehicle cannot tell."""

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None  # metres above home
    heading_deg: float | None = None
    speed_mps: float | None = None
    battery: float | None = None  # percent
    armed: bool | None = None
    mode: str | None = None
    home: tuple[float, float] | None = None
    #: (north, east, up) in m/s, where the vehicle tells it.
    velocity: tuple[float, float, float] | None = None

    @property
    def position(self) -> tuple[float, float] | None:
        if self.lat is None or self.lon is None:
            return None
        return (self.lat, self.lon)


@dataclass(frozen=True)
class Breach:
    """The vehicle is outside one of its task's limits (see :mod:`agents.envelope`).

    ``limit`` is ``"altitude"`` (``value`` and ``limit_value`` in metres above home),
    ``"geofence"`` (metres from ``centre``) or ``"speed"`` (m/s). ``target`` is where the
    recovery should bring the value: a margin inside the limit (a lower altitude, a
    smaller distance from ``centre``, a lower speed), so that the vehicle does not hover
    on the line and cross it again.
    """

    limit: str
    value: float
    limit_value: float
    target: float
    centre: tuple[float, float] | None = None
    #: Caught before it crossed: where the vehicle would have come to rest on its way
    #: out (metres above home or from ``centre``); None for a value past the limit.
    rest: float | None = None


@dataclass(frozen=True)
class Projection:
    """Where a command would take the vehicle (None fields: unchanged/unknown).

    ``velocity`` is set for a movement held by repeats (a key): the velocity it asks
    for, (north, east, up) in m/s. With the adapter's :meth:`Adapter.braking` the gate
    then predicts where the vehicle comes to rest instead of checking the projected
    point, and slows the movement down before a limit (see :mod:`agents.safety`).
    """

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    velocity: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Stopping:
    """How a vehicle stops along one axis once asked to: it goes on at its speed for
    ``reaction_s`` (the age of the position it was judged on, the way to the
    autopilot, the autopilot's ramp up to full braking), then brakes at
    ``decel_mps2``."""

    decel_mps2: float
    reaction_s: float

    def distance(self, speed: float) -> float:
        """How far it goes from ``speed`` (m/s) before it rests."""
        speed = abs(speed)
        return speed * self.reaction_s + speed * speed / (2.0 * self.decel_mps2)

    def speed_within(self, room: float) -> float:
        """The highest speed it can still stop from within ``room`` metres (0 when
        there is none): the inverse of :meth:`distance`."""
        if room <= 0:
            return 0.0
        a, t = self.decel_mps2, self.reaction_s
        return a * (math.sqrt(t * t + 2.0 * room / a) - t)


@dataclass(frozen=True)
class Braking:
    """How a vehicle stops, per axis (None: that axis is not predicted); ``hold_s``: how
    long a movement goes on after its last repeat (its key let go) before it is
    stopped, which the gate adds to each axis's reaction."""

    horizontal: Stopping | None = None
    vertical: Stopping | None = None
    hold_s: float = 0.0


#: Receives what the vehicle itself reports: ``(event name, JSON-ready data)``.
EventSink = Callable[[str, dict[str, Any]], None]
RawSink = Callable[[float, bytes], None]


class Adapter(abc.ABC):
    """Base class of vehicle adapters. Subclasses set ``name`` (their integration's)
    and are created through their integration (:mod:`agents.vehicles.registry`).

    Concurrency contract: the agent serialises calls to :meth:`execute`,
    :meth:`neutral`, :meth:`safe_action` and :meth:`envelope_recover`; :meth:`state` and
    :meth:`telemetry` may be called at any time and must not block.
    """

    name: ClassVar[str]
    #: What each fail-safe action (:meth:`safe_action`) does to this vehicle, in words
    #: that finish "<vehicle> will ...": the platform shows them to a user about to end
    #: a session and to a monitor about to stop one (sent in the agent's profile).
    safe_action_words: ClassVar[Mapping[str, str]] = {
        "stop": "stop",
        "land": "land where it is",
        "return_to_home": "go back to its home point",
    }

    def __init__(self, options: Mapping[str, Any]) -> None:
        self.options = dict(options)
        #: Where :meth:`emit` sends what the vehicle reports by itself (the autopilot
        #: link lost, a low battery, a warning): the agent sets it to forward them to
        #: the platform. Called on the event loop's thread; must not block.
        self.on_event: EventSink | None = None
        #: Where an adapter whose vehicle speaks a message protocol of its own (MAVLink)
        #: hands every message it receives, as ``(Unix seconds, the message's bytes)``:
        #: the agent's flight record keeps them (a ``.tlog``). Called on the event
        #: loop's thread; must not block.
        self.on_raw: RawSink | None = None

    # --- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:  # noqa: B027 - optional hook
        """Open ports, connect to the autopilot, start background loops."""

    async def close(self) -> None:  # noqa: B027 - optional hook
        """Leave the vehicle safe and release everything :meth:`start` opened."""

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # --- what the vehicle offers -------------------------------------------------------
    @abc.abstractmethod
    def commands(self) -> list[CommandSpec]:
        """The command vocabulary."""

    @abc.abstractmethod
    def telemetry_topics(self) -> list[str]:
        """Names of the telemetry values :meth:`telemetry` returns."""

    #: How a page shows this integration's own topics (label, unit, precision); the
    #: generic ones (battery level, altitude, ...) are described in agents.telemetry.
    telemetry_labels: ClassVar[Mapping[str, TopicInfo]] = {}

    def telemetry_info(self) -> dict[str, dict[str, Any]]:
        """Every topic of :meth:`telemetry_topics` in words: the ``telemetry_info`` the
        agent sends browsers with its ``welcome``."""
        return topics_info(self.telemetry_topics(), self.telemetry_labels)

    @abc.abstractmethod
    def telemetry(self) -> dict[str, Any]:
        """Current value of every topic (JSON-ready). Must not block."""

    @abc.abstractmethod
    def state(self) -> VehicleState:
        """Current state, for the agent's safety checks and heartbeats. Must not block."""

    # --- acting ------------------------------------------------------------------------
    @abc.abstractmethod
    async def execute(self, name: str, args: Mapping[str, Any]) -> None:
        """Carry out a checked command; return once the vehicle has applied it.

        Raises AdapterError when the vehicle refuses (obstacle ahead, autopilot said
        no, no answer in time). ``args`` are validated and defaults filled.
        """

    @abc.abstractmethod
    async def safe_action(self, action: str) -> None:
        """Make the vehicle safe: ``stop``, ``land`` or ``return_to_home``.

        Called on link loss, revocation and shutdown; an adapter maps an action its
        vehicle cannot perform to the nearest one it can (a car cannot land: it stops).
        """

    def safe_action_now(self, action: str) -> str | None:
        """What :meth:`safe_action` ``action`` would do *now*, in the words of
        :attr:`safe_action_words`, when that differs from them (a drone already landing
        goes on landing; one on the ground stops its motors); None: what they say.
        Called often; must not block."""
        return None

    async def neutral(self) -> None:  # noqa: B027 - optional hook
        """Zero the user's inputs (sticks centred, motors stopped) without ending the
        task; called when the controller changes. Default: nothing to zero."""

    async def envelope_recover(self, breach: Breach) -> str:
        """Bring the vehicle back inside a limit it has crossed, whatever crossed it.

        Called by the agent's envelope watch (serialised with :meth:`execute`, like
        every action) when :meth:`state` shows the vehicle past the task's ceiling,
        geofence or maximum speed, and again while it stays there without getting
        better. Return once the correction is under way, with a few words saying what
        was done (they go to the platform and the users). A vehicle that cannot be
        corrected now (not flying, no link) is no error: say so in the answer. Raises
        AdapterError when the vehicle refuses (reported as the action).

        Default: :meth:`safe_action` ``"stop"``, the one action every vehicle has.
        Flying vehicles override it: stopping is no answer to a ceiling.
        """
        await self.safe_action("stop")
        return "stop"

    def project(self, name: str, args: Mapping[str, Any]) -> Projection | None:
        """Where ``name`` would take the vehicle over the next second or so, for the
        altitude and geofence checks; None when the command does not move it. A
        movement held by repeats also gives its ``velocity``."""
        return None

    def braking(self) -> Braking | None:
        """How the vehicle stops now (its deceleration and reaction per axis), for the
        gate's predictions of a movement's ``velocity``; None: not known, and the gate
        checks the projected point only. Must not block."""
        return None

    async def stop_motion(self, name: str) -> None:  # noqa: B027 - optional hook
        """Stop, now, the movement ``name`` put under way, along its own axis only (a
        climb stops, the forward speed it was flying with stays); called under the
        command lock when the gate refuses ``name`` at a limit, so that a refused
        repeat does not leave the previous one to run its hold. Never raises.
        Default: nothing (the movement runs out its hold; the envelope watches)."""

    async def check_failsafe_params(
        self, expected_action: str, *, max_altitude_m: float | None = None
    ) -> list[str]:
        """Compare the vehicle's own fail-safe (an autopilot's, when the agent goes
        silent) with a task's ``expected_action`` and ceiling; called when a task
        starts. Returns the mismatches in words ([] when they agree); the agent reports
        them as ``failsafe_mismatch``. Default: [] (no fail-safe of its own: the
        agent's is the vehicle's)."""
        return []

    async def fence_set(
        self,
        action: str,
        *,
        max_altitude_m: float | None = None,
        geofence_center: tuple[float, float] | None = None,
        geofence_radius_m: float | None = None,
    ) -> list[str]:
        """Hand a task's ceiling and geofence to the vehicle's own fence (an
        autopilot's), a margin outside the agent's, with the task's fail-safe
        ``action`` as its breach action: the second line, which holds when the agent
        does not (dead, hung, cut off). Called when a task starts. Returns the problems
        in words ([] when it is set, or when the vehicle has no fence of its own); the
        agent reports them as ``autopilot_fence_failed``. Never raises. Default: []."""
        return []

    async def fence_clear(self) -> list[str]:
        """Undo :meth:`fence_set` when the task ends (not when the agent stops: the
        fence is then what holds the vehicle). Returns the problems in words. Never
        raises. Default: []."""
        return []

    def native_missions(self) -> NativeMissions | None:
        """The vehicle's own mission engine (an autopilot's AUTO, see
        :mod:`agents.vehicles.plan`), which flies a plan of plain waypoints and actions
        by itself and holds it if the agent dies; None: the agent flies every step.
        Default: None."""
        return None

    def emit(self, name: str, data: dict[str, Any]) -> None:
        """Report an event of the vehicle's own to :attr:`on_event`, if set. Never
        raises: a failing sink is logged."""
        sink = self.on_event
        if sink is None:
            return
        try:
            sink(name, data)
        except Exception:
            logger.exception("%s: on_event(%s) failed", self.name, name)

    def video_source(self) -> Any | None:
        """A video source for WebRTC (see agents.video), or None without a camera."""
        return None


@dataclass
class Simulation:
    """A running simulator, as an integration's simulator hook yields it.

    An integration's simulator module offers ``simulation(options)``: an async context
    manager (:data:`SimulatorHook`) that takes the agent's adapter options (with the
    simulator's own parameters under ``options["simulator"]``), starts the simulator
    and yields this; on exit it stops the simulator. ``options`` are the adapter
    options that drive the simulated vehicle: the input ones with what connects to the
    simulator (a UDP address, a pty path, a mock pin factory...) and without
    ``simulator``. ``simulator`` is the simulator itself (a world, a process), for tests
    and diagnostics.
    """

    options: dict[str, Any]
    simulator: Any = None


#: ``simulation(options)`` of an integration's simulator module (see :class:`Simulation`).
SimulatorHook = Callable[[Mapping[str, Any]], AbstractAsyncContextManager[Simulation]]
