"""Listening in on what the uplink tells the session owner (fleet.vehicle_events)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from fleet.vehicle_events import SessionMessage, vehicle_events, vehicle_events_set


class _Overheard:
    """The registered listener, with the calls of one method recorded (and, unless
    ``instead`` is given, passed on to it)."""

    def __init__(self, inner: Any, method: str, seen: list[dict[str, Any]], instead: Any) -> None:
        self._inner, self._method, self._seen, self._instead = inner, method, seen, instead

    def __getattr__(self, name: str) -> Any:
        real = getattr(self._inner, name)
        if name != self._method:
            return real

        def call(**kwargs: Any) -> Any:
            self._seen.append(kwargs)
            return (self._instead or real)(**kwargs)

        return call


@contextlib.contextmanager
def hearing(method: str, *, instead: Callable[..., Any] | None = None) -> Iterator[list[dict]]:
    """The keyword arguments of every call of ``method`` (``agent_connected``,
    ``agent_message``, ...) the uplink makes within the block, in order; ``instead``
    answers them in place of the registered listener."""
    seen: list[dict[str, Any]] = []
    previous = vehicle_events_set(_Overheard(vehicle_events(), method, seen, instead))
    try:
        yield seen
    finally:
        vehicle_events_set(previous)


def say(*, vehicle_id: Any, message: SessionMessage) -> None:
    """Tell the session owner ``message`` of ``vehicle_id`` as the uplink does, but with
    its exceptions raised (the uplink logs them)."""
    vehicle_events().agent_message(vehicle_id=str(vehicle_id), message=message)
