from django.urls import path

from services import views

urlpatterns = [
    path("", views.catalog, name="catalog"),
    path("healthz", views.healthz, name="healthz"),
]
