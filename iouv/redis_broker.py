"""kombu's Redis transport, whose channels report a lost connection as a connection
error (the production mode's Celery broker).

When Redis goes away, Celery's consumer first *collects* the broken connection, which
closes the task channel and detaches kombu's transport from the connection, then
*closes* the connection, which closes the channel again. If the worker holds an
unacknowledged task at that moment (every running task does: tasks are acknowledged
late) and the first close stopped half-way (the BRPOP in flight cannot be read), the
second close tries again to put that task back in Redis: the channel asks its detached
transport where Redis is and fails with ``AttributeError: 'NoneType' object has no
attribute 'hostname'``. That is no connection error, so Celery reports an
"Unrecoverable error" and the worker exits, its embedded beat with it, and no timer of
the platform runs again. The acknowledgement of a task that ends after the loss, on the
same channel, would fail the same way.

Here such a channel raises redis's ``ConnectionError`` instead, which is what kombu and
Celery expect of a lost broker: the close is abandoned, a late acknowledgement is
logged as lost, the worker reconnects. Redis still holds the unacknowledged task and
delivers it again after the visibility timeout (``CELERY_VISIBILITY_TIMEOUT_S``); the
platform's tasks are idempotent.
"""

from __future__ import annotations

from typing import Any

from kombu.transport import redis as kombu_redis
from redis.exceptions import ConnectionError as RedisConnectionError


class Channel(kombu_redis.Channel):
    def _connparams(self, asynchronous: bool = False) -> dict[str, Any]:
        """The redis-py connection parameters; raises ``ConnectionError`` once the
        transport was detached from its connection (the channel can never reach Redis
        again: the worker opens a new connection with new channels)."""
        if self.connection.client is None:
            raise RedisConnectionError("the broker connection of this channel was closed")
        # kombu's redis Channel has _connparams; its stubs leave it out.
        params: dict[str, Any] = super()._connparams(asynchronous=asynchronous)  # type: ignore[misc]
        return params


class Transport(kombu_redis.Transport):
    Channel = Channel
