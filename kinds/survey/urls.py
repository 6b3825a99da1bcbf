from django.urls import path

from kinds.survey import views

urlpatterns = [
    path("sessions/<uuid:session_id>/survey", views.survey_state, name="survey_state"),
    path("sessions/<uuid:session_id>/survey/mosaic.png", views.survey_mosaic, name="survey_mosaic"),
    path("sessions/<uuid:session_id>/survey/mosaic.kmz", views.survey_kmz, name="survey_kmz"),
]
