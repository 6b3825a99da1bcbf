from django.urls import path

from kinds.spectate import views

urlpatterns = [
    path("spectate/", views.spectate, name="spectate"),
    path("spectate/<uuid:session_id>/", views.spectate_session, name="spectate_session"),
]
