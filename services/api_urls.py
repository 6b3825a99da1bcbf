"""URLs of the JSON API, mounted at /api/ (see services.web.api and docs/api.md)."""

from django.urls import include, path, re_path

from services.web.api import api, not_found

urlpatterns = [
    path("v1/", include(api.urlpatterns(), namespace=api.urls_namespace)),
    # Last: anything else under /api/ is a JSON 404, never the HTML error page.
    re_path(r"", not_found),
]
