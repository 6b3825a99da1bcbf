"""The platform's Ed25519 signing key: signs vehicle tasks and user grants.

The key comes from ``settings.IOUV_SIGNING_KEY`` (PEM, from the environment or a
``_FILE``). Without it, and only where generated secrets are allowed
(``settings.DEV_SECRETS``: embedded mode and the test suite), a key is generated once
into ``settings.IOUV_SIGNING_KEY_PATH`` with mode 0600 and reused from then on, so every
process of one installation signs with the same key. Agents hold only the public half.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from django.conf import settings
from django.core.exceptions import ImproperlyConfigured
from django.core.signals import setting_changed
from django.dispatch import receiver

from agents.protocol import ProtocolError, generate_keypair, load_private_key


def _generated_pem(path: Path) -> str:
    """The PEM at ``path``, creating it first if missing.

    O_EXCL makes creation atomic: of several processes starting at once, one writes the
    key and the others read it, so they never end up signing with different keys.
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return path.read_text()
    private_pem, _ = generate_keypair()
    with os.fdopen(fd, "w") as handle:
        handle.write(private_pem)
    return private_pem


@functools.cache
def platform_private_key() -> Ed25519PrivateKey:
    """The platform's signing key (loaded once per process).

    Raises ImproperlyConfigured when no key is configured and generated secrets are not
    allowed, or when the configured PEM is not an Ed25519 private key.
    """
    pem = settings.IOUV_SIGNING_KEY
    source = "IOUV_SIGNING_KEY"
    if not pem:
        if not settings.DEV_SECRETS:
            raise ImproperlyConfigured(
                "Set IOUV_SIGNING_KEY or IOUV_SIGNING_KEY_FILE (an Ed25519 PEM private key)"
            )
        path = Path(settings.IOUV_SIGNING_KEY_PATH)
        path.parent.mkdir(parents=True, exist_ok=True)
        pem = _generated_pem(path)
        source = str(path)
    try:
        return load_private_key(pem)
    except ProtocolError as exc:
        raise ImproperlyConfigured(f"{source}: {exc.message}") from None


def platform_public_key() -> Ed25519PublicKey:
    """The public half of :func:`platform_private_key` (what agents verify with)."""
    return platform_private_key().public_key()


def platform_public_key_pem() -> str:
    """The public key as SubjectPublicKeyInfo PEM text, for agents' configuration."""
    return (
        platform_public_key()
        .public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        .decode("ascii")
    )


@receiver(setting_changed)
def _forget_key(*, setting: str, **kwargs: Any) -> None:
    # Tests (and override_settings) may point at another key: drop the cached one.
    if setting in ("IOUV_SIGNING_KEY", "IOUV_SIGNING_KEY_PATH", "DEV_SECRETS"):
        platform_private_key.cache_clear()
