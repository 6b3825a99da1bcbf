"""Sending to a vehicle's agent: what other apps call to reach a vehicle.

Two ways, for two kinds of traffic. What the platform tells an agent (tasks, revokes,
ends) is owed in the database until the agent acknowledges it (:func:`vehicle_send`,
fleet.outbox), whichever platform process holds its uplink. Relayed control traffic is
worthless late: it travels now, best effort, on the channel layer to the group of the
vehicle (:func:`avehicle_send`), and the uplink (fleet.uplink) writes it to the agent.
"""

from __future__ import annotations

from typing import Any

from channels.layers import get_channel_layer

from agents.protocol import encode_message
from agents.protocol.messages import EndTask, RelayClose, RelayToAgent, Revoke, Task
from fleet.outbox import agent_message_enqueue, vehicle_group


def relay_group(conn: str) -> str:
    """The channel-layer group of one relayed browser connection (``conn`` is the
    random id the relay picked)."""
    return f"relay-{conn}"


def vehicle_send(
    *, vehicle_id: Any, message: Task | Revoke | EndTask, session_id: Any = None
) -> None:
    """Tell the vehicle's agent ``message`` (a ``task``, ``revoke`` or ``end_task``),
    reliably: it is owed in the database from the current transaction on and delivered
    until the agent acknowledges it, whenever the agent is connected (fleet.outbox).
    ``session_id``: the session it is about (default: the message's own field; a
    ``task`` carries it only inside its token).

    Raises ProtocolError if ``message`` breaks the protocol's limits, ValueError for
    another type or if ``vehicle_id`` is not a UUID.
    """
    agent_message_enqueue(vehicle_id=vehicle_id, message=message, session_id=session_id)


async def avehicle_send(
    *,
    vehicle_id: Any,
    message: RelayToAgent | RelayClose,
    via: str | None = None,
    reply_to: str | None = None,
) -> None:
    """Send ``message`` to the vehicle's agent now, best effort, through the channel
    layer: for relayed control traffic, which is worthless late. It travels as the
    frame's text, encoded once here and not parsed again on the way: a relayed payload
    is a struct the relay parsed (and so checked), the rest is the platform's own.

    ``via``: the uplink's own channel, when the sender knows it (it comes with every
    answer, see :class:`AgentUplinkConsumer`): one direct send instead of a group
    lookup per command. ``reply_to``: the channel of the relayed browser, which the
    uplink then answers directly. Raises ProtocolError for a message that cannot be
    encoded or is too large, ValueError for a bad id.
    """
    group = vehicle_group(vehicle_id)
    event: dict[str, Any] = {
        "type": "agent.send",
        "text": encode_message(message),
        "conn": message.conn or None,
        "reply": reply_to if isinstance(message, RelayToAgent) else None,
    }
    layer = get_channel_layer()
    if layer is None:
        return
    if via is not None:
        await layer.send(via, event)
    else:
        await layer.group_send(group, event)
