"""WSGI entry point: the platform's HTTP (pages, API, admin) in production.

Production serves HTTP from gunicorn's worker processes (``deploy/systemd/iouv-web@.service``)
and WebSockets from uvicorn processes running ``iouv.asgi`` (``iouv-ws@.service``),
nginx routing between them by path (``deploy/nginx/iouv.conf``): each kind of traffic
on the server made for it, a slow or flooded page never in the way of an agent's
uplink. docs/operations.md describes the whole.
"""

import os

from django.core.wsgi import get_wsgi_application

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")

application = get_wsgi_application()
