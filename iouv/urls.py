"""Root URLs."""

from django.contrib import admin
from django.templatetags.static import static
from django.urls import include, path
from django.views.generic.base import RedirectView

from operations.health import healthz, readyz
from services.supervision.metrics import metrics
from services.web.keys_views import jwks

admin.site.site_header = "IoUV administration"
admin.site.site_title = "IoUV"

urlpatterns = [
    # Liveness and readiness (operations.health), first: nothing below is consulted for them.
    path("healthz", healthz, name="healthz"),
    path("readyz", readyz, name="readyz"),
    # Prometheus (services.supervision.metrics): loopback or a bearer token only.
    path("metrics", metrics, name="metrics"),
    # Pages that do not name an icon (the admin's) make browsers ask for this one.
    path("favicon.ico", RedirectView.as_view(url=static("img/favicon.svg"), permanent=True)),
    path("admin/", admin.site.urls),
    # The platform's public keys (JWKS), where agents and clients conventionally look.
    path(".well-known/jwks.json", jwks, name="jwks"),
    path("accounts/", include("accounts.urls")),
    path("api/", include("services.api_urls")),
    path("", include("services.urls")),
]
