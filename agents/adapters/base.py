"""The abstraction layer: one adapter interface for every kind of vehicle.

The agent talks to a vehicle only through an :class:`Adapter`. An adapter declares its
command vocabulary (:class:`CommandSpec`) and telemetry topics, executes commands the
agent has already checked against the task, reports the vehicle's state and performs
the safe action on a fail-safe. Adding a vehicle kind means writing one adapter and
registering it; users and service developers never see MAVLink, GPIO or serial frames.

Lifecycle: ``async with adapter_create(name, options) as adapter: ...`` calls
:meth:`Adapter.start` and, whatever happens, :meth:`Adapter.close`.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, ClassVar, Self

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


@dataclass(frozen=True)
class Projection:
    """Where a command would take the vehicle (None fields: unchanged/unknown)."""

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None


class Adapter(abc.ABC):
    """Base class of vehicle adapters. Subclasses set ``name`` and register.

    Concurrency contract: the agent serialises calls to :meth:`execute`,
    :meth:`neutral`, :meth:`safe_action` and :meth:`envelope_recover`; :meth:`state` and
    :meth:`telemetry` may be called at any time and must not block.
    """

    name: ClassVar[str]

    def __init__(self, options: Mapping[str, Any]) -> None:
        self.options = dict(options)

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
        altitude and geofence checks; None when the command does not move it."""
        return None

    def video_source(self) -> Any | None:
        """A video source for WebRTC (see agents.video), or None without a camera."""
        return None


def origin_option(options: Mapping[str, Any], adapter: str) -> tuple[float, float] | None:
    """The ``origin`` option, ``[lat, lon]`` where a simulated vehicle starts (or a real
    one without GPS counts from), or None. Raises ValueError naming the option."""
    origin = options.get("origin")
    if origin is None:
        return None
    if not isinstance(origin, Sequence) or isinstance(origin, str) or len(origin) != 2:
        raise ValueError(f"{adapter} option origin: expected [lat, lon]")
    lat, lon = float(origin[0]), float(origin[1])
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        raise ValueError(f"{adapter} option origin: latitude or longitude out of range")
    return (lat, lon)


REGISTRY: dict[str, type[Adapter]] = {}


def register(cls: type[Adapter]) -> type[Adapter]:
    """Class decorator: make an adapter available by its ``name``."""
    REGISTRY[cls.name] = cls
    return cls


def adapter_class(name: str) -> type[Adapter]:
    """The adapter class registered as ``name``.

    Adapter modules are imported on demand so an agent only loads its own vehicle's
    libraries (no pymavlink on a car). Raises KeyError naming the known adapters.
    """
    if name not in REGISTRY:
        import importlib

        try:
            importlib.import_module(f"agents.adapters.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"agents.adapters.{name}":
                raise
    if name not in REGISTRY:
        raise KeyError(f"unknown adapter {name!r}; known: {', '.join(sorted(REGISTRY))}")
    return REGISTRY[name]


def adapter_create(name: str, options: Mapping[str, Any]) -> Adapter:
    """Instantiate the adapter registered as ``name`` (see :func:`adapter_class`)."""
    return adapter_class(name)(options)
