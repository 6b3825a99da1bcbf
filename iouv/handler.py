"""Django's ASGI handler, with each request's middleware and view run in one thread hop.

Django's own ASGI handler runs the middleware chain in async mode. Every middleware
that is not async-native (all of ``settings.MIDDLEWARE``: sessions, CSRF, messages,
security headers, the content security policy) then has its ``process_request`` and
``process_response`` each sent to the request's thread and back: about fifteen trips
between the event loop and a thread for one API call, on the same interpreter lock
that carries every agent's uplink. Here the whole chain runs as Django runs it under
WSGI, synchronously, on the request's thread, reached once. Reading the body, the
request's signals and sending the response stay Django's ASGI code, on the loop.

Nothing here is async-only: every view of the platform is synchronous. An async view
would still work (Django runs it with ``async_to_sync`` on the request's thread), only
without the benefit of the loop.
"""

from __future__ import annotations

from typing import Any

from asgiref.sync import sync_to_async
from django.core.handlers import base
from django.core.handlers.asgi import ASGIHandler
from django.http import FileResponse, HttpRequest, HttpResponseBase


class OneHopASGIHandler(ASGIHandler):
    """An ASGI application serving Django over HTTP (``django.core.asgi`` sets Django up
    first, as for Django's own handler)."""

    def __init__(self) -> None:
        base.BaseHandler.__init__(self)
        self.load_middleware(is_async=False)

    async def run_get_response(self, request: HttpRequest) -> HttpResponseBase:
        # Thread-sensitive: on the request's own thread (ASGIHandler.__call__ opens a
        # ThreadSensitiveContext per request), the one the request_started and
        # request_finished signals run on, so the database connection the view used is
        # the one given back when the request finishes.
        response: Any = await sync_to_async(self.get_response, thread_sensitive=True)(request)
        response._handler_class = self.__class__
        if isinstance(response, FileResponse):
            response.block_size = self.chunk_size  # the ASGI server chunks it further
        return response  # type: ignore[no-any-return]


def one_hop_asgi_application() -> OneHopASGIHandler:
    """Like ``django.core.asgi.get_asgi_application``: Django set up, then the handler."""
    import django

    django.setup(set_prefix=False)
    return OneHopASGIHandler()
