"""Who answers what vehicle agents say on the uplink: an explicit, typed interface.

``fleet`` receives the agents' frames but does not own sessions, and must not import
``services``. The app that owns sessions implements :class:`VehicleEvents` and
registers it once when it starts (``services.apps``, with :func:`vehicle_events_set`);
the uplink calls it through the functions below. One listener, named in one place,
instead of six Django signals that each needed exactly one receiver to mean anything.

Every call is made from a worker thread (``database_sync_to_async``), so a listener
may use the ORM directly. The functions below are what the uplink calls: a listener's
exception is logged with its traceback and never reaches the uplink, so a bug in
supervision cannot drop a vehicle's connection; only the database being unavailable is
raised, for the uplink to try the report again (``AgentUplinkConsumer._until_stored``).

``vehicle_id`` is the vehicle's UUID as text. The vehicle was authenticated by its
credential before any of these is called, but the message content is the agent's word:
a listener checks that it only talks about sessions it serves.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypedDict, TypeVar

from agents.protocol.messages import Event, TaskAccepted, TaskRefused, message_type
from fleet.outbox import Acked
from operations.outages import DATABASE_UNAVAILABLE

log = logging.getLogger(__name__)

T = TypeVar("T")

#: What an agent says about sessions, handed on as it said it.
SessionMessage = TaskAccepted | TaskRefused | Event


class AgentState(TypedDict):
    """What an agent says it is doing as it registers (from its ``profile``)."""

    session_id: str | None  # the session of the task it runs, or None
    controller: bool  # a user controls it
    status: str | None  # its own status word, or None


class VehicleEvents(Protocol):
    """What the platform's session owner answers when vehicles speak."""

    def agent_connected(self, *, vehicle_id: str, state: AgentState) -> None:
        """An agent registered: it said ``hello`` with a valid credential and its
        ``profile`` has been stored. Called inside the transaction that stored it, so
        the listener converges the agent to the platform's wishes before anything else
        sees the vehicle; it does its writes in its own ``transaction.atomic()``."""
        ...

    def agent_disconnected(self, *, vehicle_id: str, code: int | None) -> None:
        """An agent's uplink closed (and no newer uplink of the same vehicle has taken
        over); the vehicle has been marked offline unless in maintenance. ``code``: the
        WebSocket close code, if any."""
        ...

    def agent_welcome(self, *, vehicle_id: str) -> dict[str, Any]:
        """Extra optional ``welcome`` fields for an agent that authenticated (e.g.
        ``platform_public_key``, which the signing key's owner knows and ``fleet`` does
        not)."""
        ...

    def agent_acked(self, *, vehicle_id: str, acked: Acked) -> None:
        """An agent acknowledged a message the platform owed it (fleet.outbox)."""
        ...

    def agent_message(self, *, vehicle_id: str, message: SessionMessage) -> None:
        """An agent sent ``task_accepted``, ``task_refused`` or ``event`` (validated
        against the uplink_to_platform table, unknown fields kept)."""
        ...

    def vehicles_back(self, *, vehicle_ids: Sequence[str]) -> None:
        """Vehicles the platform had marked offline (silent past the sweep's limit)
        were heard from again on the uplink they kept open. Called inside the
        transaction that made them available again; the listener does its writes in its
        own ``transaction.atomic()``."""
        ...


class NobodyListens:
    """The listener of a platform without a session owner: every report is dropped."""

    def agent_connected(self, *, vehicle_id: str, state: AgentState) -> None:
        pass

    def agent_disconnected(self, *, vehicle_id: str, code: int | None) -> None:
        pass

    def agent_welcome(self, *, vehicle_id: str) -> dict[str, Any]:
        return {}

    def agent_acked(self, *, vehicle_id: str, acked: Acked) -> None:
        pass

    def agent_message(self, *, vehicle_id: str, message: SessionMessage) -> None:
        pass

    def vehicles_back(self, *, vehicle_ids: Sequence[str]) -> None:
        pass


_listener: list[VehicleEvents] = [NobodyListens()]


def vehicle_events_set(listener: VehicleEvents) -> VehicleEvents:
    """Register the one listener (replacing any before it); returns the one replaced,
    so that a test can put it back."""
    previous = _listener[0]
    _listener[0] = listener
    return previous


def vehicle_events() -> VehicleEvents:
    """The registered listener, called directly (its exceptions propagate): for tests
    that speak as the uplink does and want to see a failure."""
    return _listener[0]


def _told(what: str, call: Callable[[VehicleEvents], T], otherwise: T) -> T:
    """``call`` on the listener; a failure is logged with its traceback and answered
    with ``otherwise``, but for the database being unavailable, which is raised."""
    try:
        return call(_listener[0])
    except DATABASE_UNAVAILABLE:
        raise
    except Exception:
        log.exception("uplink: the vehicle events listener failed on %s", what)
        return otherwise


def agent_connected(*, vehicle_id: str, state: AgentState) -> None:
    """Tell the listener an agent registered (see :meth:`VehicleEvents.agent_connected`)."""
    _told("agent_connected", lambda o: o.agent_connected(vehicle_id=vehicle_id, state=state), None)


def agent_disconnected(*, vehicle_id: str, code: int | None) -> None:
    """Tell the listener an uplink closed (see :meth:`VehicleEvents.agent_disconnected`)."""
    _told(
        "agent_disconnected", lambda o: o.agent_disconnected(vehicle_id=vehicle_id, code=code), None
    )


def agent_welcome(*, vehicle_id: str) -> dict[str, Any]:
    """The listener's extra ``welcome`` fields; none when it failed."""
    nothing: dict[str, Any] = {}
    extras = _told("agent_welcome", lambda o: o.agent_welcome(vehicle_id=vehicle_id), nothing)
    return extras if isinstance(extras, dict) else nothing


def agent_acked(*, vehicle_id: str, acked: Acked) -> None:
    """Tell the listener of an acknowledgement (see :meth:`VehicleEvents.agent_acked`)."""
    _told("agent_acked", lambda o: o.agent_acked(vehicle_id=vehicle_id, acked=acked), None)


def agent_message(*, vehicle_id: str, message: SessionMessage) -> None:
    """Hand the listener an agent's session message (see :meth:`VehicleEvents.agent_message`)."""
    _told(
        message_type(message),
        lambda o: o.agent_message(vehicle_id=vehicle_id, message=message),
        None,
    )


def vehicles_back(*, vehicle_ids: Sequence[str]) -> None:
    """Tell the listener silent vehicles were heard from again (see
    :meth:`VehicleEvents.vehicles_back`)."""
    _told("vehicles_back", lambda o: o.vehicles_back(vehicle_ids=vehicle_ids), None)
