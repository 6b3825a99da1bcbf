"""The platform's HTTP served by Django's own ASGI handler, for benchmarks.http_handler.

The same settings and the same concurrency limit as ``iouv.asgi``; only the handler
differs: Django's runs each middleware hook in a thread hop of its own.
"""

import os

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")

from django.core.asgi import get_asgi_application

django_asgi_app = get_asgi_application()

from django.conf import settings  # noqa: E402

from iouv.concurrency import HttpConcurrencyLimit  # noqa: E402

application = HttpConcurrencyLimit(django_asgi_app, limit=settings.IOUV_HTTP_CONCURRENCY)
