"""URLs of the JSON API, mounted at /api/ (see services.api and docs/api.md)."""

from django.urls import path, re_path

from services import api

urlpatterns = [
    path("v1/services", api.services_list, name="api_services"),
    path("v1/sessions", api.sessions_create, name="api_sessions"),
    path("v1/sessions/<uuid:session_id>", api.session_read, name="api_session"),
    path("v1/sessions/<uuid:session_id>/grant", api.session_grant, name="api_session_grant"),
    path("v1/sessions/<uuid:session_id>/end", api.session_finish, name="api_session_end"),
    path("v1/sessions/<uuid:session_id>/stop", api.session_stop, name="api_session_stop"),
    path("v1/vehicles", api.vehicles_list, name="api_vehicles"),
    path("v1/openapi.json", api.openapi, name="api_openapi"),
    # Last: anything else under /api/ is a JSON 404, never the HTML error page.
    re_path(r"", api.not_found),
]
