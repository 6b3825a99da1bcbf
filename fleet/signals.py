"""What vehicle agents say on the uplink, published for other apps.

``fleet`` must not import ``services``; the uplink consumer sends these signals instead
and ``services`` (supervision, relay) listens. Every signal is sent from a worker thread
(``database_sync_to_async``), so receivers may use the ORM directly. Receivers are
called with ``send_robust``: an exception in one is logged and never reaches the
uplink, so a bug in supervision cannot drop a vehicle's connection.

``sender`` is ``fleet.uplink.AgentUplinkConsumer``; ``vehicle_id`` is the vehicle's
UUID as text. The vehicle was authenticated by its credential before any of these is
sent, but the message content is the agent's word: receivers check that it only talks
about sessions it serves.
"""

from __future__ import annotations

from django.dispatch import Signal

#: An agent registered: it said ``hello`` with a valid credential and its ``profile``
#: has been stored. Sent inside the transaction that stored it, so receivers converge
#: the agent to the platform's wishes before anything else sees the vehicle; receivers
#: must do their writes in their own ``transaction.atomic()`` block. Kwargs:
#: ``vehicle_id``, ``state``: what the agent says it is doing, ``{"session_id": the
#: session of the task it runs or None, "controller": a user controls it, "status":
#: its own status word or None}``.
agent_connected = Signal()

#: An agent's uplink closed (and no newer uplink of the same vehicle has taken over).
#: The vehicle has been marked offline unless in maintenance. Kwargs: ``vehicle_id``,
#: ``code`` (the WebSocket close code, may be None).
agent_disconnected = Signal()

#: An agent authenticated and its ``welcome`` is being built. Receivers may return a
#: dict of extra optional ``welcome`` fields (e.g. ``platform_public_key``, which the
#: signing key's owner knows and ``fleet`` does not). Kwargs: ``vehicle_id``.
agent_welcome = Signal()

#: An agent acknowledged a message the platform owed it (fleet.outbox). Kwargs:
#: ``vehicle_id``, ``acked`` (a :class:`fleet.outbox.Acked`: the message's kind and
#: session, the agent's ``ok`` and detail, whether the vehicle left ``releasing``).
agent_acked = Signal()

#: An agent sent ``task_accepted``, ``task_refused``, ``event`` or ``relay``.
#: Kwargs: ``vehicle_id``, ``message`` (the dict from ``parse_message``: fields
#: validated against the uplink_to_platform table, unknown fields kept).
agent_message = Signal()

#: Vehicles the platform had marked offline (silent past the sweep's limit) were heard
#: from again on the uplink they kept open. Sent inside the transaction that made them
#: available again; receivers do their writes in their own ``transaction.atomic()``.
#: Kwargs: ``vehicle_ids`` (UUIDs as text).
vehicle_back = Signal()
