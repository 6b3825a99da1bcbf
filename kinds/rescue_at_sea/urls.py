from django.urls import path

from kinds.rescue_at_sea import views

urlpatterns = [
    path("sessions/<uuid:session_id>/mission", views.session_mission, name="session_mission"),
]
