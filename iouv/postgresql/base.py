"""Django's PostgreSQL backend (``ENGINE = "iouv.postgresql"``) with one change: its
pool of connections checks each one as it is lent by its socket
(:func:`iouv.db_pool.pooled_connection_check`) instead of with an empty statement.

Django builds the pool itself and always passes psycopg_pool's own check (or none),
so the pool is built here as Django builds it (Django 5.1 and 5.2), with that check.
Everything else is Django's.
"""

from __future__ import annotations

from typing import Any

from django.core.exceptions import ImproperlyConfigured
from django.db.backends.base.base import NO_DB_ALIAS
from django.db.backends.postgresql import base
from psycopg_pool import ConnectionPool

from iouv.db_pool import pooled_connection_check


class DatabaseWrapper(base.DatabaseWrapper):
    """A PostgreSQL connection whose pool (``OPTIONS["pool"]``) checks connections
    without a round trip when ``CONN_HEALTH_CHECKS`` is on."""

    @property
    def pool(self) -> ConnectionPool[Any] | None:
        options = self.settings_dict["OPTIONS"].get("pool")
        if self.alias == NO_DB_ALIAS or not options:
            return None
        # Django's, shared by every connection of the process (django-stubs omits it).
        pools: dict[str, ConnectionPool[Any]] = self._connection_pools  # type: ignore[attr-defined]
        if self.alias not in pools:
            if self.settings_dict.get("CONN_MAX_AGE", 0) != 0:
                raise ImproperlyConfigured("Pooling doesn't support persistent connections.")
            connect_kwargs = self.get_connection_params()
            # As Django: autocommit while in the pool; Django sets it when it takes one.
            connect_kwargs["autocommit"] = True
            checked = self.settings_dict["CONN_HEALTH_CHECKS"]
            pool: ConnectionPool[Any] = ConnectionPool(
                kwargs=connect_kwargs,
                open=False,  # opened on first use, as Django does
                configure=self._configure_connection,  # type: ignore[attr-defined]
                check=pooled_connection_check if checked else None,
                **({} if options is True else options),
            )
            # As Django: threads building one at start-up keep the first.
            pools.setdefault(self.alias, pool)
        return pools[self.alias]
