from django.urls import path

from services import views

urlpatterns = [
    path("", views.catalog, name="catalog"),
    path("services/<slug:slug>/", views.service_request, name="service_request"),
    path("sessions/<uuid:session_id>/", views.session_page, name="session"),
    path("sessions/<uuid:session_id>/grant", views.session_grant, name="session_grant"),
    path("sessions/<uuid:session_id>/mission", views.session_mission, name="session_mission"),
    path("sessions/<uuid:session_id>/end", views.session_finish, name="session_end"),
    path("sessions/<uuid:session_id>/stop", views.session_stop, name="session_stop"),
    path("spectate/", views.spectate, name="spectate"),
    path("spectate/<uuid:session_id>/", views.spectate_session, name="spectate_session"),
    path("monitor/", views.monitor, name="monitor"),
    path("healthz", views.healthz, name="healthz"),
]
