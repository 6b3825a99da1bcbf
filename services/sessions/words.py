"""A session log's events in words: one line a person can read for each, never a bare
code ("agent event"). The session pages list them (services.web.views.log_lines) and the
feeds carry them with each event (``text``), so a page adds new lines in the same
words.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

#: How a controller's messages reach the vehicle (Session.ControlPath), in words.
PATHS = {
    "webrtc_direct": "WebRTC, direct",
    "webrtc_turn": "WebRTC through TURN",
    "relay": "the platform's relay",
    "websocket": "the vehicle's own socket",
}
#: Why a vehicle acted on its own (an agent's ``failsafe`` cause).
CAUSES = {"link_lost": "the driver's link to the vehicle was lost"}


def _words(code: Any) -> str:
    return str(code or "").replace("_", " ")


def _who(data: Mapping[str, Any]) -> str:
    return str(data.get("vehicle_name") or data.get("name") or "the vehicle")


def _user(data: Mapping[str, Any]) -> str:
    return str(data.get("user") or "the user")


def _state(d: Mapping[str, Any]) -> str:
    reason = d.get("reason")
    return f"session {d.get('to', '?')}" + (f": {reason}" if reason else "")


def _failsafe(d: Mapping[str, Any]) -> str:
    own = f"the vehicle had to act on its own ({_words(d.get('cause'))})"
    cause = CAUSES.get(str(d.get("cause")), own)
    return f"{cause}, so it performed its fail-safe ({_words(d.get('action'))})"


def _agent_event(d: Mapping[str, Any]) -> str:
    """An event of the vehicle's the platform logs without acting on it: in the words
    of its own kind when it has some (a breach of a limit, an autopilot's warning),
    else its name in words and what it said."""
    nested = d.get("data")
    inner: Mapping[str, Any] = nested if isinstance(nested, Mapping) else d
    own = _TEXT.get(str(d.get("event")))
    if own is not None and own is not _agent_event:
        return own(inner)
    said = next((str(inner[k]) for k in ("text", "reason", "message", "words") if inner.get(k)), "")
    return f"the vehicle reported {_words(d.get('event') or 'an event')}" + (
        f": {said}" if said else ""
    )


_TEXT: dict[str, Callable[[Mapping[str, Any]], str]] = {
    "requested": lambda d: (
        "requested" + (" through the platform's relay" if d.get("relay") else "")
    ),
    "assigned": lambda d: f"{_who(d)} reserved as {d.get('role', 'vehicle')}",
    "state": _state,
    "task_deployed": lambda d: f"task sent to {_who(d)}",
    "task_accepted": lambda d: "the vehicle accepted its task",
    "record_batch": lambda d: f"flight record received: samples {d['first']} to {d['last']}",
    "record_deleted": lambda d: f"flight record deleted by {d['by']}",
    "record_video": lambda d: f"recorded video added to the flight record ({d['size']:,} bytes)",
    "task_refused": lambda d: f"the vehicle refused its task: {d.get('reason', 'no reason given')}",
    "task_ended": lambda d: f"the vehicle ended its task: {d.get('reason', '')}".rstrip(": "),
    "grant_issued": lambda d: (
        f"{_user(d)} may {'drive' if d.get('role') == 'controller' else 'watch'} the vehicle"
    ),
    "user_connected": lambda d: (
        f"{_user(d)} connected, " + ("in control" if d.get("role") == "controller" else "watching")
    ),
    "user_disconnected": lambda d: f"{_user(d)} left",
    "control_handover": lambda d: f"{_user(d)} took control from another page",
    "control_released": lambda d: f"{_user(d)} released control",
    "control_path": lambda d: (
        f"{_user(d)}'s commands go through {PATHS.get(str(d.get('path')), _words(d.get('path')))}"
    ),
    "command_refused": lambda d: (
        f"{d.get('name', 'a command')} refused: {d.get('reason') or _words(d.get('code'))}"
        + (f" ({d['count']} times)" if isinstance(d.get("count"), int) and d["count"] > 1 else "")
    ),
    "unintentional_end": _failsafe,
    "link_recovered": lambda d: (
        "the driver's link came back"
        + (f" after {d['after_ms'] / 1000:.1f} s" if isinstance(d.get("after_ms"), int) else "")
    ),
    "link_quality": lambda d: (
        "link quality measured"
        + (f": {d['rtt_ms']:.0f} ms round trip" if isinstance(d.get("rtt_ms"), int | float) else "")
    ),
    "envelope_breach": lambda d: (
        f"past the {_words(d.get('limit'))} limit; the vehicle corrects itself"
        + (f" ({_words(d.get('action'))})" if d.get("action") else "")
    ),
    "envelope_restored": lambda d: f"back inside the {_words(d.get('limit'))} limit",
    "vehicle_online": lambda d: "the vehicle is back online",
    "vehicle_offline": lambda d: "the vehicle went offline",
    "stop_delivered": lambda d: "the stop reached the vehicle",
    "end_delivered": lambda d: "the end of the session reached the vehicle",
    "vehicle_released": lambda d: f"{_who(d)} released: {d.get('reason', '')}".rstrip(": "),
    "notice_sent": lambda d: f"{_words(d.get('topic') or 'a notice')} sent ({d.get('channel')})",
    "autopilot_warning": lambda d: f"the autopilot warns: {d.get('text', '')}".rstrip(": "),
    "autopilot_link_lost": lambda d: "the agent lost its link to the autopilot",
    "autopilot_link_restored": lambda d: "the agent's link to the autopilot is back",
    "low_battery": lambda d: (
        f"low battery ({d.get('battery', '?')} %)"
        + (f": {_words(d.get('action'))}" if d.get("action") else "")
    ),
    "safe_action_failed": lambda d: (
        f"the fail-safe could not be performed: {_words(d.get('reason'))}"
    ),
    "agent_event": _agent_event,
}


def event_text(kind: str, data: Any) -> str:
    """One log event in words (see the module docstring). Kinds of their own (a
    mission's) say their ``text`` or ``reason`` when they have one."""
    d: Mapping[str, Any] = data if isinstance(data, Mapping) else {}
    words = _TEXT.get(kind)
    if words is not None:
        try:
            return words(d)
        except (KeyError, TypeError, ValueError):
            pass  # a malformed entry: said plainly below
    detail = d.get("text") or d.get("reason") or d.get("to") or ""
    return _words(kind) + (f": {detail}" if detail else "")
