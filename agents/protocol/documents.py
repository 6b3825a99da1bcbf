"""Signed documents (vehicle task, user grant) as JWTs, and replay protection.

A document is a compact JWS (RFC 7515) JWT (RFC 7519) signed by the platform with EdDSA
over Ed25519 (RFC 8037) through PyJWT; this module writes no signature encoding of its
own. The header names the signing key (``kid``, an RFC 7638 thumbprint) and the document's
purpose by explicit typing (RFC 8725 §3.11): ``typ`` is ``iouv-task+jwt`` or
``iouv-grant+jwt``, and one is never accepted as the other. Registered claims carry the
issuer, the vehicle (``aud``), the user (``sub``), the validity window (``iat``, ``nbf``,
``exp``) and a single-use id (``jti``); project claims carry the rest.
"""

from __future__ import annotations

import heapq
import json
import math
import re
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final, TypeAlias

import jwt
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from jwt.utils import base64url_decode, base64url_encode

from agents.protocol.base import (
    _LINK_LOSS_RANGE_MS,
    _MAX_TOKEN_CHARS,
    CLOCK_SKEW_S,
    DEFAULT_LINK_LOSS_TIMEOUT_MS,
    PROTOCOL_VERSION,
    REPLAY_GUARD_MAX_ENTRIES,
    Checker,
    ExpiredError,
    Kind,
    ProtocolError,
    ReplayError,
    SignatureError,
    WrongTargetError,
    _bad,
    _check_action,
    _check_id,
    _check_int,
    _check_lat,
    _check_lon,
    _check_object,
    _check_positive_number,
    _check_role,
    _check_timestamp,
    _check_version,
)
from agents.protocol.keys import ALGORITHM, KeySet, key_thumbprint

#: Who signs documents (the ``iss`` claim). Verifiers refuse any other issuer.
ISSUER: Final = "iouv-platform"

#: The ``typ`` header of each kind of document (RFC 8725 §3.11 explicit typing).
TOKEN_TYPES: Final[dict[str, str]] = {
    "vehicle_task": "iouv-task+jwt",
    "user_grant": "iouv-grant+jwt",
}

#: What a verifier accepts as the platform's key: one key, or a set named by ``kid``.
PublicKeys: TypeAlias = Ed25519PublicKey | KeySet

# Claims every document must carry; PyJWT refuses a token missing one.
_REQUIRED: Final = ("exp", "nbf", "iat", "jti", "iss", "aud", "sub")
_REGISTERED: Final = frozenset(_REQUIRED)

# Three non-empty base64url segments. PyJWT's decoder skips foreign characters, so the
# alphabet is checked first and one token never has many spellings.
_COMPACT_JWS = re.compile(r"[A-Za-z0-9_-]+\.[A-Za-z0-9_-]+\.[A-Za-z0-9_-]+")


class UnknownKeyError(SignatureError):
    """The token names a key (``kid``) the verifier does not trust, or names none while
    several keys are trusted. A SignatureError, so callers refusing bad signatures refuse
    these too; its code is ``unknown_key``."""

    def __init__(self, message: str) -> None:
        ProtocolError.__init__(self, "unknown_key", message, field="kid")


def new_nonce() -> str:
    """Return a fresh random token id (``jti``; 128 bits, URL-safe text)."""
    return secrets.token_urlsafe(16)


def _with_field(exc: ProtocolError, path: str) -> ProtocolError:
    # The base errors name the v1 field; documents now name the JWT claim.
    exc.field = path
    return exc


# --------------------------------------------------------------------------------------
# Signing and verification
# --------------------------------------------------------------------------------------


def _sign(claims: Mapping[str, Any], private_key: Ed25519PrivateKey, kind: Kind) -> str:
    """Sign ``claims`` as a compact JWT of ``kind``, naming the key by its thumbprint."""
    headers = {"kid": key_thumbprint(private_key), "typ": TOKEN_TYPES[kind]}
    return jwt.encode(dict(claims), private_key, algorithm=ALGORITHM, headers=headers)


def _check_shape(token: Any) -> None:
    """Refuse before any parsing: not text, too long, not three canonical base64url parts."""
    if not isinstance(token, str):
        raise ProtocolError("bad_token", "token must be a string")
    if len(token) > _MAX_TOKEN_CHARS:
        raise ProtocolError("bad_token", "token is too long")
    if not _COMPACT_JWS.fullmatch(token):
        raise ProtocolError("bad_token", "token must be three base64url parts joined by '.'")
    for part in token.split("."):
        try:
            canonical = base64url_encode(base64url_decode(part)).decode("ascii") == part
        except ValueError:  # binascii.Error: a length no encoding produces
            canonical = False
        if not canonical:
            raise ProtocolError("bad_token", "token part is not canonical base64url")


def _select_key(token: str, keys: PublicKeys) -> Ed25519PublicKey:
    """The trusted key the (unverified) header names. Only picks; trusts nothing else."""
    try:
        header = jwt.get_unverified_header(token)
    except jwt.PyJWTError:
        raise ProtocolError("bad_token", "token header is not a JSON object") from None
    if header.get("alg") != ALGORITHM:
        # Refused before PyJWT sees it: no 'none', no HMAC keyed with the public key.
        raise SignatureError(f"token alg must be {ALGORITHM}, not {header.get('alg')!r}")
    kid = header.get("kid")
    if kid is not None and not isinstance(kid, str):
        raise UnknownKeyError("token kid must be text")
    key_set = keys if isinstance(keys, KeySet) else KeySet.from_keys([keys])
    key = key_set.select(kid)
    if key is None:
        if kid is None:
            raise UnknownKeyError("token names no key (kid) and several keys are trusted")
        raise UnknownKeyError(f"token key {kid!r} is not one of the platform's keys")
    return key


def _decode(
    token: str,
    keys: PublicKeys,
    *,
    kind: Kind,
    vehicle_id: str,
    issuer: str,
    now: float | None,
) -> dict[str, Any]:
    """Verify ``token`` and return its claims; only ProtocolError subclasses escape.

    Order: shape and size, key by ``kid``, signature (PyJWT, EdDSA only), required claims,
    ``iss``, ``aud``; then ``typ``, ``v``, ``exp`` and ``nbf``/``iat`` against ``now``.
    Nothing in the payload is looked at before the signature has been verified.
    """
    if not isinstance(vehicle_id, str) or not vehicle_id:
        raise ValueError("vehicle_id must be the verifying agent's own non-empty id")
    _check_shape(token)
    key = _select_key(token, keys)
    try:
        decoded = jwt.decode_complete(
            token,
            key,
            algorithms=[ALGORITHM],
            audience=vehicle_id,
            issuer=issuer,
            # Times are checked below against the caller's clock (``now``), with floats.
            options={
                "require": list(_REQUIRED),
                "verify_exp": False,
                "verify_nbf": False,
                "verify_iat": False,
                "strict_aud": True,
            },
        )
    except jwt.InvalidSignatureError:
        raise SignatureError("token signature does not match the platform key") from None
    except (jwt.InvalidAlgorithmError, jwt.InvalidKeyError) as exc:
        raise SignatureError(f"token cannot be verified: {exc}") from None
    except jwt.MissingRequiredClaimError as exc:
        raise _bad(exc.claim, "is missing") from None
    except jwt.InvalidIssuerError:
        err = ProtocolError("wrong_issuer", f"token is not issued by {issuer!r}", field="iss")
        raise err from None
    except jwt.InvalidAudienceError:
        err = WrongTargetError(f"token is not addressed to vehicle {vehicle_id!r}")
        raise _with_field(err, "aud") from None
    except jwt.exceptions.InvalidSubjectError:
        raise _bad("sub", "must be a string") from None
    except jwt.exceptions.InvalidJTIError:
        raise _bad("jti", "must be a string") from None
    except jwt.PyJWTError as exc:
        # DecodeError & co: only reachable past the signature with a bad platform payload.
        raise ProtocolError("bad_token", f"token cannot be decoded: {exc}") from None
    header: dict[str, Any] = decoded["header"]
    claims: dict[str, Any] = decoded["payload"]
    if header.get("typ") != TOKEN_TYPES[kind]:
        raise ProtocolError(
            "wrong_kind",
            f"token typ is {header.get('typ')!r}, expected {TOKEN_TYPES[kind]!r}",
            field="typ",
        )
    if "v" not in claims:
        raise _bad("v", "is missing", code="bad_version")
    _check_version(claims["v"], "v")
    current = time.time() if now is None else now
    expires = _check_timestamp(claims["exp"], "exp")
    if current - CLOCK_SKEW_S > expires:
        raise ExpiredError(f"document expired at {expires} (now {current:.3f})")
    starts = max(_check_timestamp(claims["nbf"], "nbf"), _check_timestamp(claims["iat"], "iat"))
    if starts > current + CLOCK_SKEW_S:
        raise ProtocolError(
            "not_yet_valid", f"document is valid from {starts} (now {current:.3f})", field="nbf"
        )
    return claims


# --------------------------------------------------------------------------------------
# Document dataclasses
# --------------------------------------------------------------------------------------


def _check_keys(payload: Mapping[str, Any], allowed: frozenset[str], prefix: str) -> None:
    # Signed documents fail closed: a field this end does not understand may be a limit it
    # would fail to enforce, so it is refused rather than ignored.
    for key in payload:
        if key not in allowed:
            path = f"{prefix}{key}"
            raise ProtocolError("bad_field", f"field '{path}' is not known", field=path)


def _require(payload: Mapping[str, Any], keys: tuple[str, ...], prefix: str = "") -> None:
    for key in keys:
        if key not in payload:
            raise _bad(f"{prefix}{key}", "is missing")


def _check_optional(value: Any, path: str, checker: Checker) -> Any:
    return None if value is None else checker(value, path)


def _check_positive_int(value: Any, path: str) -> int:
    if _check_int(value, path) <= 0:
        raise _bad(path, "must be an integer > 0")
    return int(value)


def _whole_times(doc: VehicleTask | UserGrant) -> None:
    """Validate ``issued_at``/``expires_at`` and floor them to whole seconds.

    JWT verifiers commonly compare ``iat`` with their clock in whole seconds and no
    leeway (joserfc does): a fractional ``iat`` would be "issued in the future" for up to
    a second. Flooring moves ``iat`` earlier and ``exp`` sooner, never widening validity.
    """
    _check_timestamp(doc.issued_at, "iat")
    _check_timestamp(doc.expires_at, "exp")
    if doc.expires_at < doc.issued_at:
        raise _bad("exp", "must not be earlier than iat")
    # Frozen dataclass: normalise in place, as Limits does for geofence_center.
    object.__setattr__(doc, "issued_at", math.floor(doc.issued_at))
    object.__setattr__(doc, "expires_at", math.floor(doc.expires_at))


def _check_commands_tuple(value: Any, path: str) -> tuple[str, ...]:
    if not isinstance(value, (list, tuple)):
        raise _bad(path, "must be a list of strings")
    for i, item in enumerate(value):
        _check_id(item, f"{path}[{i}]")
    return tuple(value)


@dataclass(frozen=True, kw_only=True)
class Limits:
    """Safety limits the agent enforces for one session. ``None`` means "no limit".

    Construction validates every field and raises ProtocolError (``bad_field``, naming
    ``limits.<field>``) on a bad value, so an invalid Limits object cannot exist.
    """

    max_altitude_m: float | None = None
    #: (latitude, longitude) in degrees; set together with geofence_radius_m.
    geofence_center: tuple[float, float] | None = None
    geofence_radius_m: float | None = None
    max_speed_mps: float | None = None
    #: Silence from the controlling user after which the agent runs failsafe_action.
    link_loss_timeout_ms: int = DEFAULT_LINK_LOSS_TIMEOUT_MS
    failsafe_action: str = "stop"
    #: Past this round-trip latency the agent lowers the allowed speed.
    latency_soft_ms: int | None = None
    #: Past this round-trip latency only stop / land / return_to_home are accepted.
    latency_hard_ms: int | None = None
    session_time_limit_s: int | None = None

    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "max_altitude_m",
            "geofence_center",
            "geofence_radius_m",
            "max_speed_mps",
            "link_loss_timeout_ms",
            "failsafe_action",
            "latency_soft_ms",
            "latency_hard_ms",
            "session_time_limit_s",
        }
    )

    def __post_init__(self) -> None:
        p = "limits."
        _check_optional(self.max_altitude_m, p + "max_altitude_m", _check_positive_number)
        _check_optional(self.geofence_radius_m, p + "geofence_radius_m", _check_positive_number)
        _check_optional(self.max_speed_mps, p + "max_speed_mps", _check_positive_number)
        center = self.geofence_center
        if center is not None:
            if not isinstance(center, (list, tuple)) or len(center) != 2:
                raise _bad(p + "geofence_center", "must be [latitude, longitude]")
            normalised = (
                _check_lat(center[0], p + "geofence_center[0]"),
                _check_lon(center[1], p + "geofence_center[1]"),
            )
            # Frozen dataclass: normalise a JSON list into the declared tuple type.
            object.__setattr__(self, "geofence_center", normalised)
        if (center is None) != (self.geofence_radius_m is None):
            raise _bad(
                p + "geofence_center",
                "and geofence_radius_m must be set together (a fence needs both)",
            )
        low, high = _LINK_LOSS_RANGE_MS
        timeout = _check_int(self.link_loss_timeout_ms, p + "link_loss_timeout_ms")
        if not low <= timeout <= high:
            raise _bad(p + "link_loss_timeout_ms", f"must be in {low}..{high}")
        _check_action(self.failsafe_action, p + "failsafe_action")
        _check_optional(self.latency_soft_ms, p + "latency_soft_ms", _check_positive_int)
        _check_optional(self.latency_hard_ms, p + "latency_hard_ms", _check_positive_int)
        if (
            self.latency_soft_ms is not None
            and self.latency_hard_ms is not None
            and self.latency_soft_ms > self.latency_hard_ms
        ):
            raise _bad(p + "latency_soft_ms", "must not exceed latency_hard_ms")
        _check_optional(self.session_time_limit_s, p + "session_time_limit_s", _check_positive_int)

    def to_payload(self) -> dict[str, Any]:
        """Return the JSON-ready dict (every field present, ``None`` as null)."""
        return {
            "max_altitude_m": self.max_altitude_m,
            "geofence_center": (
                list(self.geofence_center) if self.geofence_center is not None else None
            ),
            "geofence_radius_m": self.geofence_radius_m,
            "max_speed_mps": self.max_speed_mps,
            "link_loss_timeout_ms": self.link_loss_timeout_ms,
            "failsafe_action": self.failsafe_action,
            "latency_soft_ms": self.latency_soft_ms,
            "latency_hard_ms": self.latency_hard_ms,
            "session_time_limit_s": self.session_time_limit_s,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> Limits:
        """Build Limits from a payload dict; absent fields take their defaults.

        Returns the Limits. Raises ProtocolError ``bad_field`` naming ``limits.<field>``
        for a non-object, an unknown field, or a bad value.
        """
        if not isinstance(payload, Mapping):
            raise _bad("limits", "must be an object")
        _check_keys(payload, cls._FIELDS, "limits.")
        return cls(**{str(k): v for k, v in payload.items()})


def _check_target(
    doc_vehicle: str,
    vehicle_id: str,
    nonce: str,
    expires_at: float,
    now: float | None,
    replay_guard: ReplayGuard | None,
) -> None:
    if doc_vehicle != vehicle_id:
        err = WrongTargetError(f"document is for vehicle {doc_vehicle!r}, this is {vehicle_id!r}")
        raise _with_field(err, "aud")
    # Replay last: a document refused for another reason must not burn its id.
    if replay_guard is not None:
        replay_guard.check_and_remember(nonce, expires_at, now=now)


def _check_json(value: Any, path: str) -> None:
    # PyJWT would write NaN/Infinity, which no other JSON parser reads back.
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError, RecursionError):
        raise _bad(path, "must be JSON-serialisable (no NaN/inf)") from None


def _common_claims(doc: VehicleTask | UserGrant) -> dict[str, Any]:
    """The registered claims and ``v``, shared by both kinds."""
    return {
        "iss": doc.issuer,
        "aud": doc.vehicle_id,
        "sub": doc.user,
        "iat": doc.issued_at,
        # Valid from its issue: a document is never post-dated.
        "nbf": doc.issued_at,
        "exp": doc.expires_at,
        "jti": doc.nonce,
        "v": PROTOCOL_VERSION,
    }


def _claims_checked(
    payload: Any, allowed: frozenset[str], required: tuple[str, ...]
) -> Mapping[str, Any]:
    if not isinstance(payload, Mapping):
        raise ProtocolError("bad_field", "document claims must be an object")
    _check_keys(payload, allowed, "")
    _require(payload, required)
    _check_version(payload["v"], "v")
    return payload


@dataclass(frozen=True, kw_only=True)
class VehicleTask:
    """What the platform asks one vehicle to do for one session (signed, pushed on uplink).

    Construction validates every field and raises ProtocolError (``bad_field``) naming the
    claim it travels as. ``issued_at``/``expires_at`` are Unix seconds, floored to whole
    seconds, and travel as ``iat`` (and ``nbf``)/``exp``; ``vehicle_id`` as ``aud``,
    ``user`` as ``sub``, ``nonce`` as ``jti`` and ``issuer`` as ``iss``.
    """

    KIND: ClassVar[Kind] = "vehicle_task"
    #: Every claim a task may carry; any other is refused (fail closed).
    CLAIMS: ClassVar[frozenset[str]] = _REGISTERED | {
        "v",
        "session_id",
        "allowed_commands",
        "limits",
        "mission",
    }

    session_id: str
    vehicle_id: str
    user: str
    #: Command names (from the vehicle's vocabulary) this session may send.
    allowed_commands: tuple[str, ...]
    limits: Limits
    issued_at: float
    expires_at: float
    nonce: str = field(default_factory=new_nonce)
    #: Free-form plan for autonomous tasks (e.g. waypoints); any JSON object.
    mission: dict[str, Any] | None = None
    issuer: str = ISSUER

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "aud")
        _check_id(self.user, "sub")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        if not isinstance(self.limits, Limits):
            raise _bad("limits", "must be a Limits object")
        _whole_times(self)
        _check_id(self.nonce, "jti")
        _check_id(self.issuer, "iss")
        if self.mission is not None:
            _check_object(self.mission, "mission")
            _check_json(self.mission, "mission")

    def to_payload(self) -> dict[str, Any]:
        """Return the JWT claims (registered, ``v`` and the task's own) ready for signing."""
        return {
            **_common_claims(self),
            "session_id": self.session_id,
            "allowed_commands": list(self.allowed_commands),
            "limits": self.limits.to_payload(),
            "mission": self.mission,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> VehicleTask:
        """Build a VehicleTask from (verified) claims.

        Returns the task. Raises ProtocolError naming the claim for a missing, unknown or
        bad one, ``bad_version`` for another version.
        """
        claims = _claims_checked(
            payload,
            cls.CLAIMS,
            (*_REQUIRED, "v", "session_id", "allowed_commands", "limits"),
        )
        return cls(
            session_id=claims["session_id"],
            vehicle_id=claims["aud"],
            user=claims["sub"],
            allowed_commands=_check_commands_tuple(claims["allowed_commands"], "allowed_commands"),
            limits=Limits.from_payload(claims["limits"]),
            issued_at=claims["iat"],
            expires_at=claims["exp"],
            nonce=claims["jti"],
            mission=claims.get("mission"),
            issuer=claims["iss"],
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this task as a compact JWT signed with ``private_key`` (EdDSA), its
        ``kid`` the key's thumbprint and its ``typ`` ``iouv-task+jwt``."""
        return _sign(self.to_payload(), private_key, self.KIND)

    @classmethod
    def verify(
        cls,
        token: str,
        keys: PublicKeys,
        *,
        vehicle_id: str,
        issuer: str = ISSUER,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> VehicleTask:
        """Verify a task token on the agent whose id is ``vehicle_id``.

        ``keys`` is the platform key, or a :class:`KeySet` from which the token's ``kid``
        picks one. ``now`` (Unix seconds, default ``time.time()``) is the verifier's clock;
        ``CLOCK_SKEW_S`` is tolerated on ``exp``, ``nbf`` and ``iat``.

        Order: shape, key, signature, required claims, ``iss``, ``aud``, ``typ``, ``v``,
        times, every claim's value, then, if ``replay_guard`` is given, the ``jti``.

        Returns the task. Raises only ProtocolError subclasses: SignatureError
        (``bad_signature``; UnknownKeyError ``unknown_key``), ExpiredError (``expired``),
        WrongTargetError (``wrong_vehicle``), ReplayError (``replayed``) or ProtocolError
        (``bad_token``, ``wrong_issuer``, ``wrong_kind``, ``bad_version``,
        ``not_yet_valid``, ``bad_field``); ValueError only for an empty ``vehicle_id``.
        """
        claims = _decode(token, keys, kind=cls.KIND, vehicle_id=vehicle_id, issuer=issuer, now=now)
        task = cls.from_payload(claims)
        _check_target(task.vehicle_id, vehicle_id, task.nonce, task.expires_at, now, replay_guard)
        return task


@dataclass(frozen=True, kw_only=True)
class UserGrant:
    """Permission for one user to connect to one vehicle's control socket (signed).

    The browser presents it in ``auth``. Construction validates every field and raises
    ProtocolError (``bad_field``) naming the claim (see :class:`VehicleTask`).
    """

    KIND: ClassVar[Kind] = "user_grant"
    #: Every claim a grant may carry; any other is refused (fail closed).
    CLAIMS: ClassVar[frozenset[str]] = _REGISTERED | {
        "v",
        "session_id",
        "role",
        "allowed_commands",
    }

    session_id: str
    vehicle_id: str
    user: str
    role: str
    #: Command names this user may send; a viewer normally gets an empty tuple.
    allowed_commands: tuple[str, ...]
    issued_at: float
    expires_at: float
    nonce: str = field(default_factory=new_nonce)
    issuer: str = ISSUER

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "aud")
        _check_id(self.user, "sub")
        _check_role(self.role, "role")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        _whole_times(self)
        _check_id(self.nonce, "jti")
        _check_id(self.issuer, "iss")

    def to_payload(self) -> dict[str, Any]:
        """Return the JWT claims (registered, ``v`` and the grant's own) ready for signing."""
        return {
            **_common_claims(self),
            "session_id": self.session_id,
            "role": self.role,
            "allowed_commands": list(self.allowed_commands),
        }

    @classmethod
    def from_payload(cls, payload: Any) -> UserGrant:
        """Build a UserGrant from (verified) claims.

        Returns the grant. Raises ProtocolError naming the claim for a missing, unknown or
        bad one, ``bad_version`` for another version.
        """
        claims = _claims_checked(
            payload,
            cls.CLAIMS,
            (*_REQUIRED, "v", "session_id", "role", "allowed_commands"),
        )
        return cls(
            session_id=claims["session_id"],
            vehicle_id=claims["aud"],
            user=claims["sub"],
            role=claims["role"],
            allowed_commands=_check_commands_tuple(claims["allowed_commands"], "allowed_commands"),
            issued_at=claims["iat"],
            expires_at=claims["exp"],
            nonce=claims["jti"],
            issuer=claims["iss"],
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this grant as a compact JWT signed with ``private_key`` (EdDSA), its
        ``kid`` the key's thumbprint and its ``typ`` ``iouv-grant+jwt``."""
        return _sign(self.to_payload(), private_key, self.KIND)

    @classmethod
    def verify(
        cls,
        token: str,
        keys: PublicKeys,
        *,
        vehicle_id: str,
        issuer: str = ISSUER,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> UserGrant:
        """Verify a grant presented to the agent whose id is ``vehicle_id``.

        Same arguments, order and errors as :meth:`VehicleTask.verify`. With
        ``replay_guard`` the grant's ``jti`` is consumed: a grant opens one connection, a
        reconnect needs a fresh grant from the platform.
        """
        claims = _decode(token, keys, kind=cls.KIND, vehicle_id=vehicle_id, issuer=issuer, now=now)
        grant = cls.from_payload(claims)
        _check_target(
            grant.vehicle_id, vehicle_id, grant.nonce, grant.expires_at, now, replay_guard
        )
        return grant


def claimed_session(token: Any) -> str | None:
    """The ``session_id`` a token claims, **unverified**: only to label a refusal (which
    session failed) for the platform. None when it cannot be read."""
    try:
        claims = jwt.decode(token, options={"verify_signature": False})
    except (jwt.PyJWTError, ValueError, TypeError, AttributeError):
        return None
    session = claims.get("session_id")
    return session if isinstance(session, str) and 0 < len(session) <= 100 else None


# --------------------------------------------------------------------------------------
# Replay protection
# --------------------------------------------------------------------------------------


class ReplayGuard:
    """Remembers document nonces so each signed document is accepted at most once.

    A nonce is remembered until its document could no longer pass the expiry check
    (``expires_at + CLOCK_SKEW_S``); after that the document is refused as expired anyway,
    so forgetting it is safe and keeps memory bounded. ``max_entries`` is a hard cap on
    top: when full, the oldest remembered nonce is evicted. Not thread-safe: meant for one
    asyncio loop.
    """

    def __init__(self, *, max_entries: int = REPLAY_GUARD_MAX_ENTRIES) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be >= 1")
        self._max_entries = max_entries
        # nonce -> forget-after time; dict insertion order gives "oldest" for eviction.
        self._forget_at: dict[str, float] = {}
        # (forget-after time, nonce) min-heap, so pruning touches only expired entries.
        self._heap: list[tuple[float, str]] = []

    def __len__(self) -> int:
        return len(self._forget_at)

    def __contains__(self, nonce: object) -> bool:
        return nonce in self._forget_at

    def check_and_remember(
        self, nonce: str, expires_at: float, *, now: float | None = None
    ) -> None:
        """Accept ``nonce`` once.

        Returns None and remembers the nonce when it is new. Raises ReplayError if the
        nonce was seen and its document is still valid; ProtocolError ``bad_field`` for an
        empty nonce or a non-finite ``expires_at``.
        """
        _check_id(nonce, "jti")
        _check_timestamp(expires_at, "exp")
        current = time.time() if now is None else now
        self._prune(current)
        if nonce in self._forget_at:
            raise _with_field(ReplayError("document id (jti) was already used"), "jti")
        while len(self._forget_at) >= self._max_entries:
            del self._forget_at[next(iter(self._forget_at))]
        forget_at = float(expires_at) + CLOCK_SKEW_S
        self._forget_at[nonce] = forget_at
        heapq.heappush(self._heap, (forget_at, nonce))
        if len(self._heap) > 2 * self._max_entries:
            # Evicted nonces leave stale heap entries; rebuild so the heap stays bounded.
            self._heap = [(t, n) for n, t in self._forget_at.items()]
            heapq.heapify(self._heap)

    def _prune(self, now: float) -> None:
        while self._heap and self._heap[0][0] < now:
            forget_at, nonce = heapq.heappop(self._heap)
            # The entry may be stale (evicted by the cap); only drop a matching one.
            if self._forget_at.get(nonce) == forget_at:
                del self._forget_at[nonce]
