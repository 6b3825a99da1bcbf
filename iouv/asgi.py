"""ASGI entry point: HTTP through Django, WebSockets through Channels.

Browser sockets sit behind ``AllowedHostsOriginValidator`` and session authentication.
The agent uplink does not: agents are not browsers, send no Origin header and
authenticate with their own vehicle credential inside the socket, so no cookie can
be abused cross-site there.
"""

import os
import sys

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")

from iouv.handler import one_hop_asgi_application

django_asgi_app = one_hop_asgi_application()

# Imported after Django is set up: consumers import models.
from channels.auth import AuthMiddlewareStack  # noqa: E402
from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402
from channels.security.websocket import AllowedHostsOriginValidator  # noqa: E402
from django.conf import settings  # noqa: E402

from iouv.collector import collector_tune  # noqa: E402
from iouv.concurrency import ASGIApp, HttpConcurrencyLimit  # noqa: E402
from iouv.http_limits_twisted import daphne_use_limited_channel  # noqa: E402
from iouv.routing import (  # noqa: E402
    browser_websocket_urlpatterns,
    self_authenticating_websocket_urlpatterns,
    websocket_path,
)

# Under daphne, its HTTP channel answers an oversized request head with a 414 or 431, as
# the platform's own server does (iouv.serve, iouv.http_limits), instead of dropping the
# connection. Set up whichever server imports this: daphne's app (INSTALLED_APPS, for
# runserver) has imported daphne's server and Twisted by now anyway.
daphne_use_limited_channel()

# A request's thread runs its whole view without giving the interpreter back
# (iouv.handler); the event loop, which carries every socket, waits for it at most
# this long each time it needs it (iouv.concurrency).
sys.setswitchinterval(settings.IOUV_SWITCH_INTERVAL_MS / 1000)

http_app: ASGIApp = HttpConcurrencyLimit(django_asgi_app, limit=settings.IOUV_HTTP_CONCURRENCY)
if settings.SERVE_STATIC:
    from django.contrib.staticfiles.handlers import ASGIStaticFilesHandler

    # Static files are served here, outside the limit: a page's scripts never wait
    # behind API requests.
    http_app = ASGIStaticFilesHandler(http_app)

application = ProtocolTypeRouter(
    {
        "http": http_app,
        "websocket": URLRouter(
            [
                *self_authenticating_websocket_urlpatterns,
                # Everything else is opened by browsers: origin-checked, cookie-authenticated.
                websocket_path(
                    r"^",
                    AllowedHostsOriginValidator(
                        AuthMiddlewareStack(URLRouter(browser_websocket_urlpatterns))
                    ),
                    regex=True,
                ),
            ]
        ),
    }
)

# Last: what exists now (the platform's modules, classes and schemas) lives as long as
# the process, and is kept out of every later full collection (iouv.collector).
collector_tune(settings.IOUV_GC_YOUNG_THRESHOLD)
