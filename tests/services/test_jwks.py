"""The platform's public keys at /.well-known/jwks.json, and key rotation on the platform.

A grant the platform issues must verify with an independent JOSE library (joserfc) using
only what the platform publishes: that is the promise to third-party clients and agents.
"""

from __future__ import annotations

import json
import time
from typing import Any, cast

import jwt as pyjwt
import pytest
from django.core.exceptions import ImproperlyConfigured
from django.test import Client
from django.urls import reverse
from joserfc import jwt as jose_jwt
from joserfc.jwk import KeySet as JoseKeySet

from agents.protocol import (
    KeySet,
    Limits,
    ProtocolError,
    UserGrant,
    VehicleTask,
    generate_keypair,
    key_thumbprint,
    load_private_key,
    load_public_key,
)
from services.sessions.deployment import grant_issue
from services.sessions.signing import platform_jwks, platform_keys, platform_private_key

pytestmark = [pytest.mark.filterwarnings("ignore:EdDSA is deprecated")]

OLD_PRIVATE_PEM, OLD_PUBLIC_PEM = generate_keypair()
NEW_PRIVATE_PEM, NEW_PUBLIC_PEM = generate_keypair()


def _jwks(client: Client) -> dict[str, Any]:
    answer = client.get("/.well-known/jwks.json")
    assert answer.status_code == 200
    assert answer["Content-Type"] == "application/json"
    cache = answer["Cache-Control"]
    assert "public" in cache and "max-age=300" in cache, cache
    return json.loads(answer.content)


def _grant(vehicle: str = "car-7", *, key_pem: str = NEW_PRIVATE_PEM) -> str:
    now = time.time()
    return UserGrant(
        session_id="s-1",
        vehicle_id=vehicle,
        user="alice",
        role="viewer",
        allowed_commands=(),
        issued_at=now,
        expires_at=now + 60,
    ).sign(load_private_key(key_pem))


def test_jwks_is_public_and_names_the_signing_key(client: Client) -> None:
    assert reverse("jwks") == "/.well-known/jwks.json"
    jwks = _jwks(client)  # no login
    (key,) = jwks["keys"]
    assert key["kid"] == key_thumbprint(platform_private_key())
    assert {key["kty"], key["crv"], key["alg"], key["use"]} == {"OKP", "Ed25519", "EdDSA", "sig"}
    assert "d" not in key
    assert KeySet.from_jwks(jwks) == platform_keys()


def test_jwks_refuses_other_methods(client: Client) -> None:
    assert client.post("/.well-known/jwks.json").status_code == 405


@pytest.mark.django_db
def test_a_grant_from_grant_issue_verifies_with_joserfc_and_the_published_jwks(
    client: Client,
    live_session: Any,
) -> None:
    session, vehicle_id = live_session
    token = grant_issue(session=session, user=session.user).grant
    published = JoseKeySet.import_key_set(cast(Any, _jwks(client)))
    decoded = jose_jwt.decode(token, published, algorithms=["EdDSA"])
    assert decoded.header["kid"] == key_thumbprint(platform_private_key())
    assert decoded.header["typ"] == "iouv-grant+jwt"
    registry = jose_jwt.JWTClaimsRegistry(
        aud={"essential": True, "value": vehicle_id},
        sub={"essential": True, "value": session.user.get_username()},
        iss={"essential": True},
        exp={"essential": True},
        jti={"essential": True},
    )
    registry.validate(decoded.claims)
    assert decoded.claims["session_id"] == str(session.pk)
    assert decoded.claims["role"] == "controller"


def test_rotation_overlap_publishes_both_and_accepts_both(settings: Any, client: Client) -> None:
    # Step 2 of the rotation: the new key signs, the old one is still accepted.
    settings.IOUV_SIGNING_KEY = NEW_PRIVATE_PEM
    settings.IOUV_SIGNING_PREVIOUS_KEYS = OLD_PUBLIC_PEM
    new_kid = key_thumbprint(load_public_key(NEW_PUBLIC_PEM))
    old_kid = key_thumbprint(load_public_key(OLD_PUBLIC_PEM))
    assert [k["kid"] for k in _jwks(client)["keys"]] == [new_kid, old_kid]
    now = time.time()
    task = VehicleTask(
        session_id="s-1",
        vehicle_id="car-7",
        user="alice",
        allowed_commands=(),
        limits=Limits(),
        issued_at=now,
        expires_at=now + 60,
    )
    assert pyjwt.get_unverified_header(task.sign(platform_private_key()))["kid"] == new_kid
    for token in (_grant(), _grant(key_pem=OLD_PRIVATE_PEM)):
        assert UserGrant.verify(token, platform_keys(), vehicle_id="car-7")
    # Step 4: the previous key is dropped; its tokens are refused, and it is unpublished.
    settings.IOUV_SIGNING_PREVIOUS_KEYS = ""
    assert [k["kid"] for k in platform_jwks()["keys"]] == [new_kid]
    with pytest.raises(ProtocolError) as info:
        UserGrant.verify(_grant(key_pem=OLD_PRIVATE_PEM), platform_keys(), vehicle_id="car-7")
    assert info.value.code == "unknown_key"


def test_a_bad_previous_key_is_a_configuration_error(settings: Any) -> None:
    settings.IOUV_SIGNING_PREVIOUS_KEYS = (
        "-----BEGIN PUBLIC KEY-----\nnope\n-----END PUBLIC KEY-----"
    )
    with pytest.raises(ImproperlyConfigured, match="IOUV_SIGNING_PREVIOUS_KEYS"):
        platform_jwks()
