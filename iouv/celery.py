"""The Celery app; tasks live in each app's ``tasks.py``."""

import os

from celery import Celery
from celery.signals import beat_init, worker_init

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")

app = Celery("iouv")
app.config_from_object("django.conf:settings", namespace="CELERY")
app.autodiscover_tasks()


@worker_init.connect
@beat_init.connect
def _cross_process(**kwargs: object) -> None:
    # Not the ASGI server: with the in-memory layer, pushes go through the database.
    from operations import layer

    layer.CROSS_PROCESS = True
