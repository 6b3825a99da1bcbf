"""Django's ASGI handler, with each request served in one thread hop, on a kept thread.

Django's own ASGI handler costs a request, around its view:

* the middleware chain run in async mode: every middleware that is not async-native
  (all of ``settings.MIDDLEWARE``: sessions, CSRF, messages, security headers, the
  content security policy) has its ``process_request`` and ``process_response`` each
  sent to the request's thread and back, about fifteen trips between the event loop
  and a thread for one API call, on the same interpreter lock that carries every
  agent's uplink;
* a trip of its own for the ``request_started`` signal and another for closing the
  response (the ``request_finished`` signal, which gives the database connection back);
* two new threads (asgiref 3.13, as installed: the request's own, and one that waits for
  it to end), since every request runs in a fresh ``ThreadSensitiveContext``;
* two tasks, one of which waits for the client to go away and, under uvicorn, ends
  every request by raising ``RequestAborted`` (the server reports ``http.disconnect``
  once a response is complete).

Under the scale benchmark's API load that was the largest source of the objects the
garbage collector had to find (iouv.collector): about 175 a request, left in reference
cycles (exceptions and their tracebacks, threads, executors, contexts).

Here a request takes one trip: ``request_started``, the middleware chain run as Django
runs it under WSGI, the view, and ``request_finished`` (the response closed), in that
order, on one thread; the response is then sent from the loop. The threads are kept
and reused, one per request at a time (iouv.concurrency limits how many). Only a
streaming response is closed after it has been sent, by a second trip to the same
thread, as Django does: its content is read while it is sent.

Nothing here is async-only: every view of the platform is synchronous. An async view
would still work (Django runs it with ``async_to_sync`` on the request's thread), only
without the benefit of the loop. A client that goes away while its view runs does not
cancel the view (a synchronous view cannot be stopped anyway): it runs to its end and
its response is dropped by the server.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from asgiref.sync import sync_to_async
from django.core import signals
from django.core.exceptions import RequestAborted
from django.core.handlers import base
from django.core.handlers.asgi import ASGIHandler, get_script_prefix
from django.http import FileResponse, HttpResponseBase
from django.urls import set_script_prefix

# As Django's handler declares them.
Receive = Callable[[], Awaitable[Mapping[str, Any]]]
Send = Callable[[Mapping[str, Any]], Awaitable[None]]


class OneHopASGIHandler(ASGIHandler):
    """An ASGI application serving Django over HTTP (``django.core.asgi`` sets Django up
    first, as for Django's own handler). ``threads_kept``: request threads kept for the
    next requests (more run at once if more requests come; they end after theirs)."""

    def __init__(self, *, threads_kept: int = 1) -> None:
        base.BaseHandler.__init__(self)
        self.load_middleware(is_async=False)
        self._threads_kept = max(1, threads_kept)
        self._idle: list[ThreadPoolExecutor] = []

    async def __call__(self, scope: dict[str, Any], receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            raise ValueError(f"Django can only handle ASGI/HTTP connections, not {scope['type']}.")
        # One thread per request at a time, each thread a single-worker executor: a
        # request's database connection belongs to the thread it was opened on, so the
        # trip that closes a streaming response must reach the same thread.
        thread = self._idle.pop() if self._idle else self._thread_new()
        try:
            await self._serve(scope, receive, send, thread)
        finally:
            if len(self._idle) < self._threads_kept:
                self._idle.append(thread)
            else:
                thread.shutdown(wait=False)

    @staticmethod
    def _thread_new() -> ThreadPoolExecutor:
        return ThreadPoolExecutor(max_workers=1, thread_name_prefix="iouv-request")

    async def _serve(
        self,
        scope: dict[str, Any],
        receive: Receive,
        send: Send,
        thread: ThreadPoolExecutor,
    ) -> None:
        try:
            body_file = await self.read_body(receive)
        except RequestAborted:  # the client went away before its body arrived
            return
        try:
            set_script_prefix(get_script_prefix(scope))
            # Not thread-sensitive: this request's own thread, not the process's one
            # shared thread (nothing else runs on this one meanwhile).
            response: HttpResponseBase = await sync_to_async(
                self._respond, thread_sensitive=False, executor=thread
            )(scope, body_file)
            await self.send_response(response, send)
            if response.streaming:
                await sync_to_async(response.close, thread_sensitive=False, executor=thread)()
        finally:
            body_file.close()

    def _respond(self, scope: dict[str, Any], body_file: Any) -> HttpResponseBase:
        """On the request's thread: the request from start to finish, but its sending."""
        signals.request_started.send(sender=self.__class__, scope=scope)
        request, error_response = self.create_request(scope, body_file)
        if request is None:
            assert error_response is not None  # Django gives one or the other
            response: HttpResponseBase = error_response
        else:
            response = self.get_response(request)
            response._handler_class = self.__class__  # type: ignore[attr-defined]
            if isinstance(response, FileResponse):
                response.block_size = self.chunk_size  # the ASGI server chunks it further
        if not response.streaming:
            # request_finished: the database connection goes back now, before sending.
            response.close()
        return response


def one_hop_asgi_application() -> OneHopASGIHandler:
    """Like ``django.core.asgi.get_asgi_application``: Django set up, then the handler,
    keeping as many request threads as requests may run at once (IOUV_HTTP_CONCURRENCY;
    eight when that is unlimited)."""
    import django
    from django.conf import settings

    django.setup(set_prefix=False)
    return OneHopASGIHandler(threads_kept=settings.IOUV_HTTP_CONCURRENCY or 8)
