from django.urls import path

from kinds.parcel_delivery import views

urlpatterns = [
    path("sessions/<uuid:session_id>/delivery", views.delivery_state, name="parcel_state"),
    path("track/<str:token>/", views.track, name="parcel_track"),
    path("track/<str:token>/state", views.track_state, name="parcel_track_state"),
]
