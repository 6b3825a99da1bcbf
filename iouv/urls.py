"""Root URLs."""

from django.contrib import admin
from django.urls import include, path

admin.site.site_header = "IoUV administration"
admin.site.site_title = "IoUV"

urlpatterns = [
    path("admin/", admin.site.urls),
    path("accounts/", include("accounts.urls")),
    path("api/", include("services.api_urls")),
    path("", include("services.urls")),
]
