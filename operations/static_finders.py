"""Django's static file finders, answering "not found" for a path outside their folders.

``GET /static/%2e%2e/%2e%2e/etc/passwd`` reaches the finders as ``../../etc/passwd``.
Django's own finders refuse such a path by raising ``SuspiciousFileOperation`` from
``safe_join``, and its static files handler (which serves ``/static/`` when
``SERVE_STATIC`` is on) turns only ``Http404`` into an answer: the rest became a 500 with
a traceback in the log, for any client that asked. Here such a path is simply not
found, so the handler answers 404 as for any missing file. Settings:
``STATICFILES_FINDERS``.
"""

from __future__ import annotations

from typing import Any

from django.contrib.staticfiles import finders
from django.core.exceptions import SuspiciousFileOperation


class _Contained:
    def find(self, path: str, *args: Any, **kwargs: Any) -> Any:
        try:
            return super().find(path, *args, **kwargs)  # type: ignore[misc]
        except SuspiciousFileOperation:
            return []  # what Django's finders return for a file they do not have


class FileSystemFinder(_Contained, finders.FileSystemFinder):
    """``STATICFILES_DIRS``, refusing paths that leave them as not found."""


class AppDirectoriesFinder(_Contained, finders.AppDirectoriesFinder):
    """Each app's ``static/``, refusing paths that leave it as not found."""
