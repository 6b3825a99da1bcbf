"""API tokens: issued once, stored as a digest, checked on every API request.

A token reads ``iouv_<prefix>_<secret>``. The prefix (10 hex digits, not secret) finds
the row; the secret is 32 random bytes, of which only the SHA-256 is stored. A 256-bit
random secret cannot be guessed from a dictionary, so a single fast hash is as strong
as a slow password hash and keeps authenticating every API call cheap.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from datetime import timedelta

from django.db import IntegrityError, transaction
from django.db.models import OuterRef, Q
from django.utils import timezone

from accounts.backends import permissions_cache, permissions_joined
from accounts.models import ApiToken
from accounts.users import User

SCHEME = "iouv"
PREFIX_BYTES = 5  # 10 hex digits: room for about a million tokens without retries
SECRET_BYTES = 32
# Writing last_used_at on every call would turn every read into a write; a minute's
# resolution is enough to tell a live token from a forgotten one.
LAST_USED_RESOLUTION = timedelta(minutes=1)
_MAX_TOKEN_LENGTH = 200


def _digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def token_parse(raw: str) -> tuple[str, str] | None:
    """Split a token into (prefix, secret); None when it is not shaped like one."""
    if not isinstance(raw, str) or len(raw) > _MAX_TOKEN_LENGTH:
        return None
    # The secret is URL-safe base64 and may itself contain "_": split twice only.
    parts = raw.split("_", 2)
    if len(parts) != 3 or parts[0] != SCHEME:
        return None
    prefix, secret = parts[1], parts[2]
    if len(prefix) != 2 * PREFIX_BYTES or not secret:
        return None
    try:
        int(prefix, 16)
    except ValueError:
        return None
    return prefix, secret


def token_issue(*, user: User, name: str) -> str:
    """Make a new API token for ``user`` and return it as ``iouv_<prefix>_<secret>``.

    The plain value exists only in the return value: show it once. Raises ValueError
    for an empty name.
    """
    name = name.strip()
    if not name:
        raise ValueError("a token needs a name")
    secret = secrets.token_urlsafe(SECRET_BYTES)
    for _ in range(5):
        prefix = secrets.token_hex(PREFIX_BYTES)
        try:
            with transaction.atomic():
                ApiToken.objects.create(
                    user=user, name=name[:100], prefix=prefix, digest=_digest(secret)
                )
        except IntegrityError:
            continue  # prefix already taken: draw another
        return f"{SCHEME}_{prefix}_{secret}"
    raise RuntimeError("could not find a free token prefix")  # pragma: no cover


def token_authenticate(raw: str) -> User | None:
    """The active user ``raw`` belongs to, else None (never raises on bad input).

    None for a malformed, unknown, forged or revoked token and for an inactive user.
    The digest is compared in constant time. Records the use at most once a minute.
    """
    parsed = token_parse(raw)
    if parsed is None:
        return None
    prefix, secret = parsed
    # With its user and the user's permissions (accounts.backends), in one query.
    token: ApiToken | None = (
        ApiToken.objects.select_related("user")
        .annotate(permissions=permissions_joined(OuterRef("user_id")))
        .filter(prefix=prefix, revoked_at__isnull=True)
        .order_by("pk")
        .first()
    )
    if token is None or not hmac.compare_digest(token.digest, _digest(secret)):
        return None
    if not token.user.is_active:
        return None
    permissions_cache(token.user, token.permissions)  # type: ignore[attr-defined]
    now = timezone.now()
    if token.last_used_at is None or token.last_used_at < now - LAST_USED_RESOLUTION:
        # Conditional so that concurrent requests do not all write.
        ApiToken.objects.filter(pk=token.pk).filter(
            Q(last_used_at__isnull=True) | Q(last_used_at__lt=now - LAST_USED_RESOLUTION)
        ).update(last_used_at=now)
    return token.user


def token_revoke(*, token: ApiToken) -> ApiToken:
    """Revoke ``token``: it stops working at once. Revoking twice keeps the first time."""
    with transaction.atomic():
        ApiToken.objects.filter(pk=token.pk, revoked_at__isnull=True).update(
            revoked_at=timezone.now()
        )
    token.refresh_from_db()
    return token


def token_for_raw(raw: str) -> ApiToken | None:
    """The row of a plain token by its prefix (valid or not), e.g. right after issue."""
    parsed = token_parse(raw)
    return ApiToken.objects.filter(prefix=parsed[0]).first() if parsed else None
