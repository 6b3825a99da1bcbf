"""ASGI entry point: HTTP through Django's own ASGI handler, WebSockets through Channels.

In production only WebSockets (``/ws/``) reach this application: nginx sends HTTP to
gunicorn (``iouv.wsgi``). The demo and the integration tests serve both from one
process (``iouv.serve``).

Browser sockets sit behind ``AllowedHostsOriginValidator`` and session authentication.
The agent uplink does not: agents are not browsers, send no Origin header and
authenticate with their own vehicle credential inside the socket, so no cookie can
be abused cross-site there.
"""

import os
from typing import Any

from django.core.asgi import get_asgi_application

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")

django_asgi_app = get_asgi_application()

# Imported after Django is set up: consumers import models.
from channels.auth import AuthMiddlewareStack  # noqa: E402
from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402
from channels.security.websocket import AllowedHostsOriginValidator  # noqa: E402
from django.conf import settings  # noqa: E402

from iouv.routing import (  # noqa: E402
    browser_websocket_urlpatterns,
    self_authenticating_websocket_urlpatterns,
    websocket_path,
)
from operations.collector import collector_tune  # noqa: E402
from operations.layer import ServerLoop  # noqa: E402

http_app: Any = django_asgi_app
if settings.SERVE_STATIC:
    from django.contrib.staticfiles.handlers import ASGIStaticFilesHandler

    # Where no nginx serves /static/ (the demo, the tests): the pages' own files.
    http_app = ASGIStaticFilesHandler(django_asgi_app)

application = ServerLoop(
    ProtocolTypeRouter(
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
)

# Last: what exists now (the platform's modules, classes and schemas) lives as long as
# the process, and is kept out of every later full collection (operations.collector).
collector_tune(settings.IOUV_GC_YOUNG_THRESHOLD)
