"""API tokens: how third-party programs authenticate to the JSON API (see accounts.tokens)."""

from __future__ import annotations

from django.conf import settings
from django.db import models


class ApiToken(models.Model):
    """A bearer token for the JSON API, held by one user and acting as that user.

    The token is ``iouv_<prefix>_<secret>``; only the SHA-256 of the secret is kept, so
    the plain token is shown once, when it is issued, and never again. The prefix is
    not secret: it finds the row and tells tokens apart in lists.
    """

    user = models.ForeignKey(
        settings.AUTH_USER_MODEL, on_delete=models.CASCADE, related_name="api_tokens"
    )
    name = models.CharField(max_length=100, help_text="What the token is for, e.g. 'rescue app'.")
    prefix = models.CharField(max_length=16, unique=True, editable=False)
    digest = models.CharField(max_length=64, editable=False)
    created_at = models.DateTimeField(auto_now_add=True)
    last_used_at = models.DateTimeField(
        null=True, blank=True, editable=False, help_text="Updated at most once a minute."
    )
    # Revoked tokens are kept, not deleted, so the admin still shows who had one and when.
    revoked_at = models.DateTimeField(null=True, blank=True, editable=False)

    class Meta:
        ordering = ["-created_at"]
        verbose_name = "API token"

    def __str__(self) -> str:
        return f"{self.name} ({self.display})"

    @property
    def display(self) -> str:
        """The token as it may be shown after issue: prefix only, secret elided."""
        return f"iouv_{self.prefix}_…"

    @property
    def is_active(self) -> bool:
        return self.revoked_at is None
