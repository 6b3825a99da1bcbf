"""The platform's Ed25519 signing key: signs vehicle tasks and user grants.

The key comes from ``settings.IOUV_SIGNING_KEY`` (PEM, from the environment or a
``_FILE``). Without it, and only where generated secrets are allowed
(``settings.DEV_SECRETS``: embedded mode and the test suite), a key is generated once
into ``settings.IOUV_SIGNING_KEY_PATH`` with mode 0600 and reused from then on, so every
process of one installation signs with the same key. Agents hold only the public half.

During a key rotation ``settings.IOUV_SIGNING_PREVIOUS_KEYS`` lists the public PEMs of the
keys signed with before: tokens they signed still verify (:func:`platform_keys`) and they
stay in the published JWKS (:func:`platform_jwks`, served at ``/.well-known/jwks.json``)
until they are dropped. docs/protocol.md, "Key rotation", gives the steps.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from django.conf import settings
from django.core.exceptions import ImproperlyConfigured
from django.core.signals import setting_changed
from django.dispatch import receiver

from agents.protocol import (
    KeySet,
    ProtocolError,
    generate_keypair,
    jwks_from_keys,
    load_private_key,
    load_public_keys,
    public_key_pem,
)


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
    return public_key_pem(platform_public_key())


@functools.cache
def platform_previous_keys() -> tuple[Ed25519PublicKey, ...]:
    """The previous signing keys still accepted during a rotation (maybe none).

    Raises ImproperlyConfigured when IOUV_SIGNING_PREVIOUS_KEYS holds anything but
    Ed25519 public keys in PEM.
    """
    try:
        keys = load_public_keys(settings.IOUV_SIGNING_PREVIOUS_KEYS or "")
    except ProtocolError as exc:
        raise ImproperlyConfigured(f"IOUV_SIGNING_PREVIOUS_KEYS: {exc.message}") from None
    current = platform_public_key().public_bytes_raw()
    # The current key listed as previous too (a half-done rotation) is listed once.
    return tuple(k for k in keys if k.public_bytes_raw() != current)


def platform_keys() -> KeySet:
    """Every key a platform token may be signed with: the current one, then the previous
    ones. What the platform itself verifies grants with."""
    return KeySet.from_keys([platform_public_key(), *platform_previous_keys()])


def platform_jwks() -> dict[str, Any]:
    """The JWK Set of :func:`platform_keys` (RFC 7517), each key named by its RFC 7638
    thumbprint, which is the ``kid`` of the tokens it signs."""
    return jwks_from_keys([platform_public_key(), *platform_previous_keys()])


@receiver(setting_changed)
def _forget_key(*, setting: str, **kwargs: Any) -> None:
    # Tests (and override_settings) may point at another key: drop the cached one.
    if setting in ("IOUV_SIGNING_KEY", "IOUV_SIGNING_KEY_PATH", "DEV_SECRETS"):
        platform_private_key.cache_clear()
        platform_previous_keys.cache_clear()
    if setting == "IOUV_SIGNING_PREVIOUS_KEYS":
        platform_previous_keys.cache_clear()
