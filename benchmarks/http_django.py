"""The platform's HTTP served by Django's own ASGI handler, for benchmarks.http_handler.

The platform's own set-up (``iouv.asgi``: settings, the interpreter's switch interval,
daphne's HTTP channel) and the same concurrency limit; only the handler differs:
Django's runs each middleware hook in a thread hop of its own.
"""

from django.conf import settings
from django.core.asgi import get_asgi_application

import iouv.asgi  # noqa: F401 - the platform's set-up, as the other handler has it
from iouv.concurrency import HttpConcurrencyLimit

application = HttpConcurrencyLimit(get_asgi_application(), limit=settings.IOUV_HTTP_CONCURRENCY)
