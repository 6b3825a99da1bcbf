"""IoUV platform project: settings, ASGI routing and the Celery app."""

from iouv.celery import app as celery_app

__all__ = ["celery_app"]
