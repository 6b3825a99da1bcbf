"""Signed documents as JWTs: what a verifier accepts and refuses, keys, rotation, replay.

Tokens are checked against a second, independent JOSE library (joserfc) both ways, so
"standard JWT" is a tested property and not just a claim.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import hmac
import json
import math
from typing import Any, cast

import jwt as pyjwt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from joserfc import jwt as jose_jwt
from joserfc.errors import BadSignatureError
from joserfc.jwk import KeySet as JoseKeySet
from joserfc.jwk import OKPKey

from agents.protocol import (
    CLOCK_SKEW_S,
    ISSUER,
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    ExpiredError,
    KeySet,
    Limits,
    ProtocolError,
    ReplayError,
    ReplayGuard,
    SignatureError,
    UnknownKeyError,
    UserGrant,
    VehicleTask,
    WrongTargetError,
    claimed_session,
    jwks_from_keys,
    key_thumbprint,
    new_nonce,
)
from tests.agents.documents import (
    NOW,
    OTHER_PRIVATE,
    OTHER_PUBLIC,
    OTHER_PUBLIC_PEM,
    PRIVATE,
    PRIVATE_PEM,
    PUBLIC,
    PUBLIC_PEM,
    make_grant,
    make_task,
)

# joserfc warns that RFC 9864 prefers the fully specified "Ed25519" name; PyJWT signs
# with "EdDSA" (RFC 8037), which both libraries and the protocol use.
pytestmark = pytest.mark.filterwarnings("ignore:EdDSA is deprecated")


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def parts(token: str) -> tuple[dict[str, Any], dict[str, Any], str]:
    header, claims, signature = token.split(".")
    return json.loads(unb64(header)), json.loads(unb64(claims)), signature


def pyjwt_token(
    claims: dict[str, Any], *, key: Any = PRIVATE, typ: str = "iouv-grant+jwt", **headers: Any
) -> str:
    """A token signed by PyJWT directly, as a platform bug or an attacker would make one."""
    headers = {"kid": key_thumbprint(key), "typ": typ, **headers}
    return pyjwt.encode(claims, key, algorithm="EdDSA", headers=headers)


def refused(
    token: Any, cls: type[UserGrant] | type[VehicleTask] = UserGrant, **kwargs: Any
) -> ProtocolError:
    kwargs = {"vehicle_id": "car-7", "now": NOW, **kwargs}
    with pytest.raises(ProtocolError) as info:
        cls.verify(token, kwargs.pop("keys", PUBLIC), **kwargs)
    return info.value


# ---------------------------------------------------------------------------------------
# Round trips and the standard format
# ---------------------------------------------------------------------------------------


def test_task_round_trip() -> None:
    task = make_task()
    assert VehicleTask.verify(task.sign(PRIVATE), PUBLIC, vehicle_id="car-7", now=NOW) == task


def test_grant_round_trip() -> None:
    grant = make_grant(role="viewer", allowed_commands=())
    assert UserGrant.verify(grant.sign(PRIVATE), PUBLIC, vehicle_id="car-7", now=NOW) == grant


def test_token_is_a_jwt_with_registered_claims_kid_and_explicit_type() -> None:
    header, claims, _ = parts(make_task().sign(PRIVATE))
    assert header == {"alg": "EdDSA", "kid": key_thumbprint(PUBLIC), "typ": "iouv-task+jwt"}
    assert claims["iss"] == ISSUER and claims["aud"] == "car-7" and claims["sub"] == "alice"
    assert claims["iat"] == claims["nbf"] == NOW and claims["exp"] == NOW + 60
    assert claims["v"] == PROTOCOL_VERSION == 2
    assert claims["limits"]["max_speed_mps"] == 3.0
    assert {"vehicle_id", "user", "nonce", "kind"}.isdisjoint(claims)
    assert parts(make_grant().sign(PRIVATE))[0]["typ"] == "iouv-grant+jwt"


def test_times_travel_as_whole_seconds() -> None:
    # joserfc (no leeway) would call a fractional iat "issued in the future".
    grant = make_grant(issued_at=NOW + 0.9, expires_at=NOW + 60.5)
    assert (grant.issued_at, grant.expires_at) == (NOW, NOW + 60)
    _, claims, _ = parts(grant.sign(PRIVATE))
    assert claims["iat"] == claims["nbf"] == NOW and isinstance(claims["iat"], int)
    assert claims["exp"] == NOW + 60 and isinstance(claims["exp"], int)


def test_kid_is_the_rfc7638_thumbprint_joserfc_computes() -> None:
    assert key_thumbprint(PUBLIC) == OKPKey.import_key(PUBLIC_PEM).thumbprint()
    assert key_thumbprint(PRIVATE) == key_thumbprint(PUBLIC)
    assert key_thumbprint(OTHER_PUBLIC) != key_thumbprint(PUBLIC)


def test_grant_signed_here_verifies_with_joserfc() -> None:
    grant = make_grant(issued_at=1_000.0, expires_at=4_000_000_000.0)
    token = grant.sign(PRIVATE)
    key = OKPKey.import_key(PUBLIC_PEM)
    decoded = jose_jwt.decode(token, key, algorithms=["EdDSA"])
    assert decoded.header["typ"] == "iouv-grant+jwt"
    assert decoded.header["kid"] == key.thumbprint()
    registry = jose_jwt.JWTClaimsRegistry(
        iss={"essential": True, "value": ISSUER},
        aud={"essential": True, "value": "car-7"},
        sub={"essential": True, "value": "alice"},
        jti={"essential": True, "value": grant.nonce},
    )
    registry.validate(decoded.claims)  # raises on a wrong or missing claim, or expiry
    assert decoded.claims["role"] == "controller"
    assert decoded.claims["allowed_commands"] == ["drive", "stop"]
    # joserfc refuses it under the wrong key: it really checked the signature.
    with pytest.raises(BadSignatureError):
        jose_jwt.decode(token, OKPKey.import_key(OTHER_PUBLIC_PEM), algorithms=["EdDSA"])


def test_token_made_by_joserfc_verifies_here() -> None:
    key = OKPKey.import_key(PRIVATE_PEM)
    claims = make_grant().to_payload()
    token = jose_jwt.encode(
        {"alg": "EdDSA", "kid": key.thumbprint(), "typ": "iouv-grant+jwt"},
        claims,
        key,
        algorithms=["EdDSA"],
    )
    assert UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW) == make_grant(
        nonce=claims["jti"]
    )


def test_claimed_session_labels_a_refusal_without_verifying() -> None:
    assert claimed_session(make_task(session_id="s-9").sign(OTHER_PRIVATE)) == "s-9"
    assert claimed_session("garbage") is None
    assert claimed_session(12) is None


# ---------------------------------------------------------------------------------------
# Refusals
# ---------------------------------------------------------------------------------------


def test_signature_from_another_key_with_our_kid_refused() -> None:
    token = pyjwt_token(make_grant().to_payload(), key=OTHER_PRIVATE, kid=key_thumbprint(PUBLIC))
    error = refused(token)
    assert type(error) is SignatureError and error.code == "bad_signature"


def test_token_from_an_unknown_key_refused_as_unknown_key() -> None:
    error = refused(make_grant().sign(OTHER_PRIVATE))
    assert isinstance(error, SignatureError)  # callers catching bad signatures catch it
    assert isinstance(error, UnknownKeyError) and error.code == "unknown_key"
    assert error.field == "kid"


def test_tampered_claims_refused() -> None:
    header, claims, signature = make_task().sign(PRIVATE).split(".")
    payload = json.loads(unb64(claims))
    payload["limits"]["max_speed_mps"] = 50.0
    forged = f"{header}.{b64(json.dumps(payload).encode())}.{signature}"
    assert refused(forged, VehicleTask).code == "bad_signature"


def test_tampered_signature_refused() -> None:
    header, claims, signature = make_task().sign(PRIVATE).split(".")
    raw = bytearray(unb64(signature))
    raw[10] ^= 1
    assert refused(f"{header}.{claims}.{b64(bytes(raw))}", VehicleTask).code == "bad_signature"


def test_alg_none_refused() -> None:
    claims = b64(json.dumps(make_grant().to_payload()).encode())
    for header in (
        {"alg": "none", "typ": "iouv-grant+jwt"},
        {"alg": "none", "kid": key_thumbprint(PUBLIC), "typ": "iouv-grant+jwt"},
    ):
        unsigned = f"{b64(json.dumps(header).encode())}.{claims}."
        assert refused(unsigned).code in {"bad_token", "bad_signature"}
        # Even with something in the signature slot, 'none' is not an algorithm we take.
        assert refused(unsigned + "c2lnbmF0dXJl").code == "bad_signature"


def test_hs256_keyed_with_the_public_key_refused() -> None:
    # The classic confusion: an attacker HMACs with the (public) verification key.
    header = {"alg": "HS256", "kid": key_thumbprint(PUBLIC), "typ": "iouv-grant+jwt"}
    signing_input = (
        f"{b64(json.dumps(header).encode())}.{b64(json.dumps(make_grant().to_payload()).encode())}"
    )
    for secret in (PUBLIC_PEM.encode(), PUBLIC.public_bytes_raw()):
        mac = hmac.new(secret, signing_input.encode(), hashlib.sha256).digest()
        assert refused(f"{signing_input}.{b64(mac)}").code == "bad_signature"


def test_grant_presented_as_task_refused_and_vice_versa() -> None:
    assert refused(make_grant().sign(PRIVATE), VehicleTask).code == "wrong_kind"
    error = refused(make_task().sign(PRIVATE), UserGrant)
    assert error.code == "wrong_kind" and error.field == "typ"
    # A token without the project's type (a generic "JWT") is neither.
    assert refused(pyjwt_token(make_grant().to_payload(), typ="JWT")).code == "wrong_kind"


def test_other_vehicle_refused() -> None:
    for token, cls in (
        (make_task().sign(PRIVATE), VehicleTask),
        (make_grant().sign(PRIVATE), UserGrant),
    ):
        error = refused(token, cls, vehicle_id="boat-1")
        assert isinstance(error, WrongTargetError)
        assert error.code == "wrong_vehicle" and error.field == "aud"


def test_audience_list_refused() -> None:
    claims = {**make_grant().to_payload(), "aud": ["boat-1", "car-7"]}
    assert refused(pyjwt_token(claims)).code == "wrong_vehicle"


def test_other_issuer_refused() -> None:
    token = make_grant(issuer="someone-else").sign(PRIVATE)
    error = refused(token)
    assert error.code == "wrong_issuer" and error.field == "iss"
    # A verifier told to expect that issuer takes it.
    assert UserGrant.verify(token, PUBLIC, vehicle_id="car-7", issuer="someone-else", now=NOW)


def test_expired_refused_but_skew_tolerated() -> None:
    token = make_task().sign(PRIVATE)
    expires = NOW + 60
    assert VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=expires + CLOCK_SKEW_S)
    error = refused(token, VehicleTask, now=expires + CLOCK_SKEW_S + 0.01)
    assert isinstance(error, ExpiredError) and error.code == "expired"


def test_not_yet_valid_refused_but_skew_tolerated() -> None:
    token = make_grant().sign(PRIVATE)
    assert UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW - CLOCK_SKEW_S)
    error = refused(token, now=NOW - CLOCK_SKEW_S - 0.01)
    assert error.code == "not_yet_valid" and error.field == "nbf"
    # nbf later than iat counts too.
    later = pyjwt_token({**make_grant().to_payload(), "nbf": NOW + 30})
    assert refused(later, now=NOW + 10).code == "not_yet_valid"


def test_signature_checked_before_expiry_and_claims() -> None:
    token = pyjwt_token(
        {**make_grant().to_payload(), "exp": 1.0, "v": 99},
        key=OTHER_PRIVATE,
        kid=key_thumbprint(PUBLIC),
    )
    assert refused(token).code == "bad_signature"


def test_other_version_refused_even_if_signed() -> None:
    assert refused(pyjwt_token({**make_grant().to_payload(), "v": 1})).code == "bad_version"
    claims = make_grant().to_payload()
    del claims["v"]
    assert refused(pyjwt_token(claims)).code == "bad_version"


@pytest.mark.parametrize("claim", ["iss", "aud", "sub", "iat", "nbf", "exp", "jti"])
def test_missing_registered_claim_refused_naming_it(claim: str) -> None:
    claims = make_grant().to_payload()
    del claims[claim]
    error = refused(pyjwt_token(claims))
    assert error.code == "bad_field" and error.field == claim


def test_signed_unknown_claim_refused_fail_closed() -> None:
    claims = {**make_grant().to_payload(), "admin": True}
    assert refused(pyjwt_token(claims)).field == "admin"
    task_claims = make_task().to_payload()
    task_claims["limits"]["max_depth_m"] = 5
    error = refused(pyjwt_token(task_claims, typ="iouv-task+jwt"), VehicleTask)
    assert error.field == "limits.max_depth_m"


@pytest.mark.parametrize(
    "claim, value",
    [
        ("jti", 7),
        ("sub", ["alice"]),
        ("exp", "tomorrow"),
        ("exp", NOW - 1),  # before iat
        ("allowed_commands", "drive"),
        ("role", "pilot"),
    ],
)
def test_bad_claim_values_refused_naming_the_claim(claim: str, value: Any) -> None:
    error = refused(pyjwt_token({**make_grant().to_payload(), claim: value}))
    assert error.code == "bad_field" and error.field == claim


@pytest.mark.parametrize(
    "path, value",
    [
        ("limits.max_speed_mps", math.inf),  # PyJWT writes and reads "Infinity"
        ("limits.max_speed_mps", True),
        ("limits.link_loss_timeout_ms", 500.0),
        ("limits.geofence_center", [43.7]),
        ("limits.geofence_center.1", 181),
        ("limits.failsafe_action", "explode"),
        ("mission", {"x": math.nan}),  # no kind: not a mission
        ("mission.altitude_m", math.nan),
        ("mission.kind", "dance"),  # a mission this agent does not know
        ("mission.waypoints", []),
        ("type", "task"),  # an unknown claim, whatever its name
        ("", "x"),
    ],
)
def test_bad_task_claims_refused_naming_the_path(path: str, value: Any) -> None:
    claims = make_task().to_payload()
    *outer, last = path.split(".")
    target = claims
    for key in outer:
        target = target[key]
    target[int(last) if isinstance(target, list) else last] = value
    error = refused(pyjwt_token(claims, typ="iouv-task+jwt"), VehicleTask)
    assert error.code == "bad_field"
    if path == "mission" and isinstance(value, dict):
        assert error.field == "mission.kind"  # what a mission needs first
    else:
        assert error.field == path.replace(".1", "[1]")


def test_constructed_values_normalised_as_verified_ones() -> None:
    task = make_task(
        allowed_commands=["drive"],
        limits=Limits(geofence_center=[43, 7], geofence_radius_m=200, max_speed_mps=3),
    )
    assert task.allowed_commands == ("drive",)
    assert task.limits.geofence_center == (43.0, 7.0)
    assert type(task.limits.max_speed_mps) is int  # as written, not converted
    assert VehicleTask.verify(task.sign(PRIVATE), PUBLIC, vehicle_id="car-7", now=NOW) == task


@pytest.mark.parametrize(
    "token",
    ["", ".", "..", "a.b.c", "abc", "!!!.???.***", "YQ.YQ", "YQ==.YQ.YQ", "e30.e30.", 12, None],
)
def test_malformed_tokens_refused(token: Any) -> None:
    assert refused(token).code in {"bad_token", "bad_signature", "unknown_key"}


def test_huge_token_refused() -> None:
    assert refused("A" * (MAX_MESSAGE_BYTES + 1)).code == "bad_token"


def test_non_canonical_base64_spelling_refused() -> None:
    token = make_grant().sign(PRIVATE)
    head, sig = token.rsplit(".", 1)
    # Flip the unused low bits of the last signature character: same bytes, other spelling.
    alphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_"
    variant = sig[:-1] + alphabet[alphabet.index(sig[-1]) ^ 1]
    assert unb64(variant) == unb64(sig)
    assert refused(f"{head}.{variant}").code == "bad_token"


def test_constructing_a_document_names_the_claim() -> None:
    for overrides, claim in (
        ({"vehicle_id": ""}, "aud"),
        ({"user": 7}, "sub"),
        ({"nonce": ""}, "jti"),
        ({"issuer": ""}, "iss"),
        ({"expires_at": NOW - 1}, "exp"),
        ({"mission": {"x": math.inf}}, "mission"),
    ):
        with pytest.raises(ProtocolError) as info:
            make_task(**overrides)
        assert info.value.field == claim


def test_fresh_ids() -> None:
    assert len({new_nonce() for _ in range(100)}) == 100
    assert make_task().nonce != make_task().nonce


# ---------------------------------------------------------------------------------------
# Key sets, JWKS and rotation
# ---------------------------------------------------------------------------------------


def test_rotation_old_key_verifies_while_listed_then_is_refused() -> None:
    old_token = make_grant().sign(OTHER_PRIVATE)  # signed before the switch
    new_token = make_grant().sign(PRIVATE)
    overlap = KeySet.from_keys([PUBLIC, OTHER_PUBLIC])
    for token in (old_token, new_token):
        assert UserGrant.verify(token, overlap, vehicle_id="car-7", now=NOW)
    after = KeySet.from_keys([PUBLIC])
    assert UserGrant.verify(new_token, after, vehicle_id="car-7", now=NOW)
    assert refused(old_token, keys=after).code == "unknown_key"


def test_jwks_lists_current_and_previous_and_round_trips() -> None:
    jwks = jwks_from_keys([PUBLIC, OTHER_PUBLIC])
    assert [k["kid"] for k in jwks["keys"]] == [
        key_thumbprint(PUBLIC),
        key_thumbprint(OTHER_PUBLIC),
    ]
    for jwk in jwks["keys"]:
        assert jwk["kty"] == "OKP" and jwk["crv"] == "Ed25519" and "d" not in jwk
        assert jwk["alg"] == "EdDSA" and jwk["use"] == "sig"
    assert KeySet.from_jwks(jwks) == KeySet.from_keys([PUBLIC, OTHER_PUBLIC])
    # joserfc reads the same set and picks the key by kid.
    token = make_grant(issued_at=1.0, expires_at=4e9).sign(OTHER_PRIVATE)
    decoded = jose_jwt.decode(
        token, JoseKeySet.import_key_set(cast(Any, jwks)), algorithms=["EdDSA"]
    )
    assert decoded.claims["aud"] == "car-7"


def test_jwks_exported_by_joserfc_is_accepted() -> None:
    jwks = JoseKeySet([OKPKey.import_key(PUBLIC_PEM)]).as_dict()
    keys = KeySet.from_jwks(jwks)
    assert UserGrant.verify(make_grant().sign(PRIVATE), keys, vehicle_id="car-7", now=NOW)


def test_missing_kid_accepted_with_one_key_refused_with_several() -> None:
    token = pyjwt.encode(
        make_grant().to_payload(), PRIVATE, algorithm="EdDSA", headers={"typ": "iouv-grant+jwt"}
    )
    assert UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW)
    error = refused(token, keys=KeySet.from_keys([PUBLIC, OTHER_PUBLIC]))
    assert error.code == "unknown_key"


def test_key_set_from_several_pem_blocks() -> None:
    keys = KeySet.from_pem(PUBLIC_PEM + OTHER_PUBLIC_PEM)
    assert keys.kids == [key_thumbprint(PUBLIC), key_thumbprint(OTHER_PUBLIC)]


@pytest.mark.parametrize(
    "jwk",
    [
        {"kty": "RSA", "n": "AQAB", "e": "AQAB"},
        {"kty": "EC", "crv": "P-256", "x": "AA", "y": "AA"},
        {"kty": "OKP", "crv": "X25519", "x": b64(bytes(32))},
        {"kty": "OKP", "crv": "Ed25519"},
        {"kty": "OKP", "crv": "Ed25519", "x": "not-32-bytes"},
        {"kty": "OKP", "crv": "Ed25519", "x": b64(PUBLIC.public_bytes_raw()), "use": "enc"},
        {"kty": "OKP", "crv": "Ed25519", "x": b64(PUBLIC.public_bytes_raw()), "alg": "RS256"},
        {"kty": "oct", "k": "c2VjcmV0"},
        "not a key",
    ],
)
def test_jwks_with_a_foreign_key_refused(jwk: Any) -> None:
    with pytest.raises(ProtocolError) as info:
        KeySet.from_jwks({"keys": [jwk]})
    assert info.value.code == "bad_key"


def test_jwks_with_private_material_or_no_keys_refused() -> None:
    private = OKPKey.import_key(PRIVATE_PEM).as_dict(private=True)
    bad: list[Any] = [{"keys": [private]}, {"keys": []}, {}, [], {"keys": "x"}]
    for jwks in bad:
        with pytest.raises(ProtocolError) as info:
            KeySet.from_jwks(jwks)
        assert info.value.code == "bad_key"
    repeated = jwks_from_keys([PUBLIC, PUBLIC])
    with pytest.raises(ProtocolError):
        KeySet.from_jwks(repeated)


# ---------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------


def test_replay_refused_then_pruned_after_expiry() -> None:
    guard = ReplayGuard()
    guard.check_and_remember("n1", NOW + 10, now=NOW)
    with pytest.raises(ReplayError) as info:
        guard.check_and_remember("n1", NOW + 10, now=NOW + 5)
    assert info.value.code == "replayed" and info.value.field == "jti"
    # Once the document could no longer pass the expiry check, the id is forgotten.
    guard.check_and_remember("n2", NOW + 100, now=NOW + 10 + CLOCK_SKEW_S + 1)
    assert "n1" not in guard
    assert len(guard) == 1


def test_replayed_jti_refused_and_fresh_grant_accepted() -> None:
    guard = ReplayGuard()
    token = make_grant().sign(PRIVATE)
    UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW, replay_guard=guard)
    with pytest.raises(ReplayError):
        UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW + 1, replay_guard=guard)
    fresh = make_grant().sign(PRIVATE)
    UserGrant.verify(fresh, PUBLIC, vehicle_id="car-7", now=NOW + 1, replay_guard=guard)


def test_same_jti_in_a_task_and_a_grant_is_one_id() -> None:
    guard = ReplayGuard()
    VehicleTask.verify(
        make_task(nonce="n").sign(PRIVATE), PUBLIC, vehicle_id="car-7", now=NOW, replay_guard=guard
    )
    with pytest.raises(ReplayError):
        UserGrant.verify(
            make_grant(nonce="n").sign(PRIVATE),
            PUBLIC,
            vehicle_id="car-7",
            now=NOW,
            replay_guard=guard,
        )


def test_refused_document_does_not_burn_its_jti() -> None:
    guard = ReplayGuard()
    token = make_task().sign(PRIVATE)
    with pytest.raises(WrongTargetError):
        VehicleTask.verify(token, PUBLIC, vehicle_id="x", now=NOW, replay_guard=guard)
    with pytest.raises(ExpiredError):
        VehicleTask.verify(token, PUBLIC, vehicle_id="car-7", now=NOW + 999, replay_guard=guard)
    assert len(guard) == 0


def test_replay_guard_cap_evicts_oldest() -> None:
    guard = ReplayGuard(max_entries=3)
    for i in range(5):
        guard.check_and_remember(f"n{i}", NOW + 1000, now=NOW)
    assert len(guard) == 3
    assert "n0" not in guard and "n4" in guard


# ---------------------------------------------------------------------------------------
# Fuzz: whatever arrives, verification answers with a ProtocolError or a valid document
# ---------------------------------------------------------------------------------------

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=8,
)


@FUZZ
@given(
    token=st.text()
    | st.from_regex(r"[A-Za-z0-9_-]{0,80}\.[A-Za-z0-9_-]{0,120}\.[A-Za-z0-9_-]{0,90}")
)
def test_fuzz_verify_text(token: str) -> None:
    with pytest.raises(ProtocolError):
        UserGrant.verify(token, PUBLIC, vehicle_id="car-7", now=NOW)


@FUZZ
@given(
    body=st.binary(max_size=200),
    header=st.dictionaries(st.text(max_size=5), json_values, max_size=3),
)
def test_fuzz_validly_signed_garbage(body: bytes, header: dict[str, Any]) -> None:
    # Past the signature the claims are trusted bytes; a platform bug there must still
    # surface as ProtocolError, never as a crash in the agent.
    # A generated "alg" header would be PyJWT's algorithm for signing: the platform's is
    # EdDSA, whatever else the header says.
    headers = {**header, "alg": "EdDSA", "kid": key_thumbprint(PUBLIC), "typ": "iouv-grant+jwt"}
    token = pyjwt.api_jws.encode(body, PRIVATE, algorithm="EdDSA", headers=headers)
    for cls in (VehicleTask, UserGrant):
        with contextlib.suppress(ProtocolError):
            cls.verify(token, PUBLIC, vehicle_id="car-7", now=NOW)


@FUZZ
@given(
    extra=st.dictionaries(
        st.sampled_from(sorted(VehicleTask.CLAIMS | UserGrant.CLAIMS | {"other"})),
        json_values,
        max_size=6,
    ),
    base=st.sampled_from(["task", "grant"]),
)
def test_fuzz_signed_claims(extra: dict[str, Any], base: str) -> None:
    claims = (make_task() if base == "task" else make_grant()).to_payload()
    claims.update(extra)
    try:
        body = json.dumps(claims).encode()
    except ValueError:
        return
    for typ in ("iouv-task+jwt", "iouv-grant+jwt"):
        headers = {"kid": key_thumbprint(PUBLIC), "typ": typ}
        token = pyjwt.api_jws.encode(body, PRIVATE, algorithm="EdDSA", headers=headers)
        for cls in (VehicleTask, UserGrant):
            with contextlib.suppress(ProtocolError):
                cls.verify(token, PUBLIC, vehicle_id="car-7", now=NOW, replay_guard=ReplayGuard())


@FUZZ
@given(position=st.integers(min_value=0, max_value=600), char=st.sampled_from("A_-.x=Q"))
def test_fuzz_mutated_token_never_verifies(position: int, char: str) -> None:
    token = make_grant(nonce="fixed").sign(PRIVATE)
    index = position % len(token)
    mutated = token[:index] + char + token[index + 1 :]
    if mutated == token:
        return
    try:
        UserGrant.verify(mutated, PUBLIC, vehicle_id="car-7", now=NOW)
    except ProtocolError:
        return
    pytest.fail(f"mutated token verified: {mutated}")
