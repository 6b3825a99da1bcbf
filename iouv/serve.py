"""The platform's server: uvicorn serving ``iouv.asgi`` as production runs it.

``python -m iouv.serve --host 127.0.0.1 --port 8001``.
The production layout's WebSocket processes (``deploy/systemd/iouv-ws@.service``,
behind nginx, which sends them ``/ws/`` only), the demo (bin/demo), the integration
tests (tests/servers.py) and the scale benchmark all start the platform with this, so
they run one configuration. The choices, all uvicorn's public settings, and why
(:data:`OPTIONS`):

* **uvloop and httptools**: the event loop and HTTP parser in C. Measured against
  daphne on the same application (docs/benchmarks/scale, "The server"), a heartbeat
  costs about a third less CPU and a process carries about a third more sessions.
* **No head limits here**: httptools sets none on a request's line or headers. In
  production nginx refuses an oversized head before it reaches any platform process
  (``deploy/nginx/iouv.conf``: ``client_header_buffer_size``,
  ``large_client_header_buffers``; tests/integration/test_head_limits.py): a process
  that anyone but its own machine can reach belongs behind nginx. (uvicorn's h11
  parser bounds a head, ``h11_max_incomplete_event_size``, answered with a 400, at
  the cost of parsing in Python.)
* **websockets-sansio**: uvicorn's WebSocket protocol on the ``websockets`` library's
  current core (the agents' own library). uvicorn's older ``websockets`` protocol can
  leave a consumer waiting forever on a send to a client that closes at that moment;
  the relay then never hears the close, and the vehicle keeps a controller who left.
* **No per-message compression**: control frames are small, and compressing them costs
  CPU on both ends (the agents never offer it; browsers do).
* **No lifespan**: ``iouv.asgi`` routes HTTP and WebSockets only; Django needs no
  start-up hook.
* **No access log, no proxy headers**: one log line per request would be most of a
  busy process's log; the platform does not use the client's address, and whether a
  request came over TLS is Django's call (``BEHIND_PROXY``, ``iouv/settings.py``).
* **Keep-alive longer than nginx's**: nginx keeps idle upstream connections for 60 s;
  a server closing them sooner races nginx reusing one, and the request on it fails.
* **Graceful shutdown bounded**: on SIGTERM, open WebSockets are closed (1012, the
  agents reconnect elsewhere) and requests in progress get 10 s to finish.

WebSocket keepalive is uvicorn's: a socket silent for 20 s is pinged and dropped when
the pong has not come 20 s later. Agents heartbeat every ``IOUV_HEARTBEAT_INTERVAL_S``
and ping every 10 s themselves, so a live agent never reaches it.
"""

from __future__ import annotations

import argparse
import faulthandler
import sys
from typing import Any

#: The application, as uvicorn imports it.
APPLICATION = "iouv.asgi:application"

#: uvicorn's settings for every platform process (see the module for why).
OPTIONS: dict[str, Any] = {
    "loop": "uvloop",
    "http": "httptools",
    "ws": "websockets-sansio",
    "ws_per_message_deflate": False,
    "ws_ping_interval": 20.0,
    "ws_ping_timeout": 20.0,
    "lifespan": "off",
    "access_log": False,
    "proxy_headers": False,
    "server_header": False,
    "timeout_keep_alive": 75,
    "timeout_graceful_shutdown": 10,
    # Django's LOGGING (iouv/settings.py) configures the log, uvicorn's lines included.
    "log_config": None,
}


def command(*, host: str = "127.0.0.1", port: int) -> list[str]:
    """The command line that serves the platform on ``host``:``port`` with this
    interpreter (for tests and benchmarks that start it as a child process)."""
    return [sys.executable, "-m", "iouv.serve", "--host", host, "--port", str(port)]


def main(argv: list[str] | None = None) -> None:
    """Serve the platform until SIGINT or SIGTERM."""
    parser = argparse.ArgumentParser(
        prog="python -m iouv.serve", description="Serve the IoUV platform (uvicorn)."
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on")
    parser.add_argument("--port", type=int, default=8000, help="port to listen on")
    args = parser.parse_args(argv)
    # A crash in an extension's C code (seen once: a segfault in msgspec under the test
    # suite's load) then leaves every thread's Python stack in the log.
    faulthandler.enable()

    import uvicorn

    uvicorn.run(APPLICATION, host=args.host, port=args.port, **OPTIONS)


if __name__ == "__main__":
    main()
