"""The portal's URLs, and those of every installed service kind (at the root)."""

from django.urls import include, path

from services.kinds import kinds
from services.web import record_views, views


def _kind_urls() -> list:  # type: ignore[type-arg]
    return [path("", include(kind.urls)) for kind in kinds() if kind.urls]


urlpatterns = [
    path("", views.catalog, name="catalog"),
    path("services/<slug:slug>/", views.service_request_page, name="service_request"),
    path("sessions/<uuid:session_id>/", views.session_page, name="session"),
    path("sessions/<uuid:session_id>/grant", views.session_grant, name="session_grant"),
    path("sessions/<uuid:session_id>/end", views.session_finish, name="session_end"),
    path("sessions/<uuid:session_id>/stop", views.session_stop, name="session_stop"),
    path("sessions/<uuid:session_id>/record/", record_views.session_record, name="session_record"),
    path("sessions/<uuid:session_id>/replay/", record_views.session_replay, name="session_replay"),
    path(
        "sessions/<uuid:session_id>/replay/video/<int:index>.webm",
        record_views.session_replay_video,
        name="session_replay_video",
    ),
    path(
        "sessions/<uuid:session_id>/replay/samples",
        record_views.session_replay_samples,
        name="session_replay_samples",
    ),
    path(
        "sessions/<uuid:session_id>/record/<str:name>",
        record_views.session_record_export,
        name="session_record_export",
    ),
    path("monitor/", views.monitor, name="monitor"),
    path("map/land.geo.json", views.land_map, name="land_map"),
    *_kind_urls(),
]
