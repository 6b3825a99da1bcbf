"""Checking a pooled database connection as it is lent, without a round trip.

psycopg_pool's own check (``ConnectionPool.check_connection``, which Django hands the
pool when ``CONN_HEALTH_CHECKS`` is on) sends an empty statement and waits for its
answer every time a connection is lent: one more round trip for every request and for
every database step of a consumer (an agent's ack, a report, the outbox), each a wait
on PostgreSQL and a hand-over of the interpreter lock. Under the scale benchmark's API
load it was about 3 % of the platform process's CPU, and two of a request's eleven
round trips were not its own.

An idle connection that PostgreSQL still holds has nothing to read: PostgreSQL only
speaks when asked (the platform does not LISTEN). When PostgreSQL ends a connection
(a restart, ``pg_terminate_backend``, an idle timeout) it sends a FATAL error and
closes the socket, and a firewall that resets it leaves it readable too. So a socket
with something to read is the sign of a dead or odd connection, and only then is the
full check run, which raises for a dead one: the pool throws it away and lends
another. A connection cut without a word (a network partition) passes, as it would
pass the empty statement's send, and fails its request's first statement.
"""

from __future__ import annotations

import select
from typing import Any

import psycopg
from psycopg import pq
from psycopg_pool import ConnectionPool


def pooled_connection_check(conn: psycopg.Connection[Any]) -> None:
    """psycopg_pool's ``check``: return if ``conn`` can be lent, raise if not.

    Runs the pool's full check (an empty statement) only when the connection is not
    plainly idle and quiet: closed, in a transaction, or with data waiting on its socket.
    """
    if conn.closed:  # closed, or broken (psycopg counts a broken connection closed)
        raise psycopg.OperationalError("the connection is closed")
    pgconn = conn.pgconn
    quiet = (
        pgconn.status == pq.ConnStatus.OK
        and pgconn.transaction_status == pq.TransactionStatus.IDLE
        and not _readable(pgconn.socket)
    )
    if not quiet:
        ConnectionPool.check_connection(conn)


def _readable(fd: int) -> bool:
    # poll, not select: a process holding a thousand uplinks has descriptors past
    # select's limit of 1024.
    poller = select.poll()
    poller.register(fd, select.POLLIN | select.POLLERR | select.POLLHUP)
    return bool(poller.poll(0))
