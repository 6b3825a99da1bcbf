"""Signed documents (vehicle task, user grant), signing keys and replay protection."""

from __future__ import annotations

import base64
import binascii
import heapq
import json
import re
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

from agents.protocol.base import (
    _LINK_LOSS_RANGE_MS,
    _MAX_TOKEN_CHARS,
    _SIGNATURE_BYTES,
    CLOCK_SKEW_S,
    DEFAULT_LINK_LOSS_TIMEOUT_MS,
    KINDS,
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
from agents.protocol.messages import _loads

# --------------------------------------------------------------------------------------
# Keys
# --------------------------------------------------------------------------------------


def generate_keypair() -> tuple[str, str]:
    """Create a new platform signing key.

    Returns ``(private_pem, public_pem)``: PKCS#8 unencrypted private key and
    SubjectPublicKeyInfo public key, both PEM text. Raises nothing.
    """
    private_key = Ed25519PrivateKey.generate()
    private_pem = private_key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    ).decode("ascii")
    public_pem = (
        private_key.public_key()
        .public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
        .decode("ascii")
    )
    return private_pem, public_pem


def load_private_key(pem: str) -> Ed25519PrivateKey:
    """Load an unencrypted PEM private key.

    Returns the key. Raises ProtocolError ``bad_key`` if the text is not a PEM private key
    or the key is not Ed25519 (the only algorithm the agents accept).
    """
    try:
        key = serialization.load_pem_private_key(pem.encode("utf-8"), password=None)
    except (ValueError, TypeError, UnsupportedAlgorithm, AttributeError) as exc:
        raise ProtocolError("bad_key", f"not a usable PEM private key: {exc}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise ProtocolError("bad_key", "private key is not an Ed25519 key")
    return key


def load_public_key(pem: str) -> Ed25519PublicKey:
    """Load a PEM public key.

    Returns the key. Raises ProtocolError ``bad_key`` if the text is not a PEM public key or
    the key is not Ed25519.
    """
    try:
        key = serialization.load_pem_public_key(pem.encode("utf-8"))
    except (ValueError, TypeError, UnsupportedAlgorithm, AttributeError) as exc:
        raise ProtocolError("bad_key", f"not a usable PEM public key: {exc}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise ProtocolError("bad_key", "public key is not an Ed25519 key")
    return key


# --------------------------------------------------------------------------------------
# Signed documents
# --------------------------------------------------------------------------------------

_B64URL = re.compile(r"[A-Za-z0-9_-]*")


def _b64url_encode(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _b64url_decode(text: str, part: str) -> bytes:
    # Strict: Python's decoder silently skips foreign characters, which would give one
    # document many spellings. Require the alphabet and the canonical encoding.
    if not _B64URL.fullmatch(text) or len(text) % 4 == 1:
        raise ProtocolError("bad_token", f"token {part} is not unpadded base64url")
    try:
        data = base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
    except (binascii.Error, ValueError):
        raise ProtocolError("bad_token", f"token {part} is not unpadded base64url") from None
    if _b64url_encode(data) != text:
        raise ProtocolError("bad_token", f"token {part} is not canonical base64url")
    return data


def _canonical_json(payload: Mapping[str, Any]) -> bytes:
    """Deterministic JSON so one payload always yields the same token."""
    return json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False).encode(
        "ascii"
    )


def _check_header(payload: Mapping[str, Any]) -> None:
    """Check the fields every signed document carries: v, kind, exp."""
    if "v" not in payload:
        raise _bad("v", "is missing", code="bad_version")
    _check_version(payload["v"], "v")
    kind = payload.get("kind")
    if not isinstance(kind, str) or kind not in KINDS:
        raise _bad("kind", f"must be one of {sorted(KINDS)}")
    if "exp" not in payload:
        raise _bad("exp", "is missing")
    _check_timestamp(payload["exp"], "exp")


def sign_document(payload: Mapping[str, Any], private_key: Ed25519PrivateKey) -> str:
    """Sign ``payload`` with the platform key.

    ``payload`` must carry ``v`` (= :data:`PROTOCOL_VERSION`), ``kind`` (one of
    :data:`KINDS`) and a finite ``exp`` (Unix seconds): a document that never expires or
    whose purpose is ambiguous is refused rather than signed.

    Returns the token ``base64url(canonical JSON) + "." + base64url(signature)`` (no
    padding). Raises ProtocolError (``bad_field``/``bad_version``) for a missing or bad
    header field or a payload that is not JSON-serialisable.
    """
    if not isinstance(payload, Mapping):
        raise ProtocolError("bad_field", "payload must be a mapping")
    _check_header(payload)
    try:
        body = _canonical_json(payload)
    except (TypeError, ValueError, RecursionError) as exc:
        raise ProtocolError("bad_field", f"payload is not JSON-serialisable: {exc}") from None
    signature = private_key.sign(body)
    return f"{_b64url_encode(body)}.{_b64url_encode(signature)}"


def verify_document(
    token: str,
    public_key: Ed25519PublicKey,
    *,
    kind: Kind | None = None,
    now: float | None = None,
) -> dict[str, Any]:
    """Verify a token made by :func:`sign_document` and return its payload.

    Order: token shape, signature, JSON object, ``v``, ``kind``, ``exp``. The signature is
    checked before the payload is even parsed, so unauthenticated bytes never reach the
    JSON parser. With ``kind`` given, a document of the other kind is refused: a user
    grant is never accepted as a vehicle task or the reverse.

    ``now`` (Unix seconds, default ``time.time()``) is the verifier's clock; the document
    is expired when ``now > exp + CLOCK_SKEW_S``.

    Returns the payload dict. Raises only ProtocolError subclasses: SignatureError
    (``bad_signature``), ExpiredError (``expired``), or ProtocolError with ``bad_token``
    (malformed token), ``bad_version``, ``wrong_kind`` or ``bad_field``.
    """
    if not isinstance(token, str):
        raise ProtocolError("bad_token", "token must be a string")
    if len(token) > _MAX_TOKEN_CHARS:
        raise ProtocolError("bad_token", "token is too long")
    parts = token.split(".")
    if len(parts) != 2:
        raise ProtocolError("bad_token", "token must be two base64url parts joined by '.'")
    body = _b64url_decode(parts[0], "payload")
    signature = _b64url_decode(parts[1], "signature")
    if len(signature) != _SIGNATURE_BYTES:
        raise SignatureError("token signature has the wrong length")
    try:
        public_key.verify(signature, body)
    except InvalidSignature:
        raise SignatureError("token signature does not match the platform key") from None
    try:
        payload = _loads(body.decode("utf-8"))
    except (ValueError, RecursionError):
        # Only reachable with a validly signed bad payload: a platform bug.
        raise ProtocolError("bad_token", "token payload is not valid JSON") from None
    if not isinstance(payload, dict):
        raise ProtocolError("bad_token", "token payload must be a JSON object")
    _check_header(payload)
    if kind is not None and payload["kind"] != kind:
        raise ProtocolError(
            "wrong_kind",
            f"document is a {payload['kind']}, expected a {kind}",
            field="kind",
        )
    current = time.time() if now is None else now
    if current - CLOCK_SKEW_S > payload["exp"]:
        raise ExpiredError(f"document expired at {payload['exp']} (now {current:.3f})")
    return payload


def new_nonce() -> str:
    """Return a fresh random nonce (128 bits, URL-safe text) for a signed document."""
    return secrets.token_urlsafe(16)


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


def _check_times(issued_at: Any, expires_at: Any) -> None:
    _check_timestamp(issued_at, "iat")
    _check_timestamp(expires_at, "exp")
    if expires_at < issued_at:
        raise _bad("exp", "must not be earlier than iat")


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


def _verify_common(
    token: str,
    public_key: Ed25519PublicKey,
    kind: Kind,
    vehicle_id: str,
    now: float | None,
) -> dict[str, Any]:
    if not isinstance(vehicle_id, str) or not vehicle_id:
        raise ValueError("vehicle_id must be the verifying agent's own non-empty id")
    return verify_document(token, public_key, kind=kind, now=now)


def _check_target(
    doc_vehicle: str,
    vehicle_id: str,
    nonce: str,
    expires_at: float,
    now: float | None,
    replay_guard: ReplayGuard | None,
) -> None:
    if doc_vehicle != vehicle_id:
        raise WrongTargetError(f"document is for vehicle {doc_vehicle!r}, this is {vehicle_id!r}")
    # Replay last: a document refused for another reason must not burn its nonce.
    if replay_guard is not None:
        replay_guard.check_and_remember(nonce, expires_at, now=now)


@dataclass(frozen=True, kw_only=True)
class VehicleTask:
    """What the platform asks one vehicle to do for one session (signed, pushed on uplink).

    Construction validates every field and raises ProtocolError (``bad_field``) naming the
    field. ``issued_at``/``expires_at`` are Unix seconds and travel as ``iat``/``exp``.
    """

    KIND: ClassVar[Kind] = "vehicle_task"
    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "v",
            "kind",
            "session_id",
            "vehicle_id",
            "user",
            "allowed_commands",
            "limits",
            "iat",
            "exp",
            "nonce",
            "mission",
        }
    )

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

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "vehicle_id")
        _check_id(self.user, "user")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        if not isinstance(self.limits, Limits):
            raise _bad("limits", "must be a Limits object")
        _check_times(self.issued_at, self.expires_at)
        _check_id(self.nonce, "nonce")
        if self.mission is not None:
            _check_object(self.mission, "mission")
            try:
                _canonical_json(self.mission)
            except (TypeError, ValueError, RecursionError):
                raise _bad("mission", "must be JSON-serialisable (no NaN/inf)") from None

    def to_payload(self) -> dict[str, Any]:
        """Return the document payload (with ``v`` and ``kind``) ready for signing."""
        return {
            "v": PROTOCOL_VERSION,
            "kind": self.KIND,
            "session_id": self.session_id,
            "vehicle_id": self.vehicle_id,
            "user": self.user,
            "allowed_commands": list(self.allowed_commands),
            "limits": self.limits.to_payload(),
            "iat": self.issued_at,
            "exp": self.expires_at,
            "nonce": self.nonce,
            "mission": self.mission,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> VehicleTask:
        """Build a VehicleTask from a (verified) payload.

        Returns the task. Raises ProtocolError naming the field for a missing, unknown or
        bad field, ``bad_version`` for another version and ``wrong_kind`` for a grant.
        """
        if not isinstance(payload, Mapping):
            raise ProtocolError("bad_field", "document payload must be an object")
        _check_keys(payload, cls._FIELDS, "")
        _require(
            payload,
            (
                "v",
                "kind",
                "session_id",
                "vehicle_id",
                "user",
                "allowed_commands",
                "limits",
                "iat",
                "exp",
                "nonce",
            ),
        )
        _check_version(payload["v"], "v")
        if payload["kind"] != cls.KIND:
            raise ProtocolError("wrong_kind", f"document kind must be {cls.KIND}", field="kind")
        return cls(
            session_id=payload["session_id"],
            vehicle_id=payload["vehicle_id"],
            user=payload["user"],
            allowed_commands=_check_commands_tuple(payload["allowed_commands"], "allowed_commands"),
            limits=Limits.from_payload(payload["limits"]),
            issued_at=payload["iat"],
            expires_at=payload["exp"],
            nonce=payload["nonce"],
            mission=payload.get("mission"),
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this task as a signed token (see :func:`sign_document`)."""
        return sign_document(self.to_payload(), private_key)

    @classmethod
    def verify(
        cls,
        token: str,
        public_key: Ed25519PublicKey,
        *,
        vehicle_id: str,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> VehicleTask:
        """Verify a task token on the agent whose id is ``vehicle_id``.

        Order: :func:`verify_document` (shape, signature, version, kind, expiry), fields,
        target vehicle, then, if ``replay_guard`` is given, the nonce.

        Returns the task. Raises SignatureError, ExpiredError, WrongTargetError,
        ReplayError or ProtocolError; ValueError only for an empty ``vehicle_id`` argument.
        """
        payload = _verify_common(token, public_key, cls.KIND, vehicle_id, now)
        task = cls.from_payload(payload)
        _check_target(task.vehicle_id, vehicle_id, task.nonce, task.expires_at, now, replay_guard)
        return task


@dataclass(frozen=True, kw_only=True)
class UserGrant:
    """Permission for one user to connect to one vehicle's control socket (signed).

    The browser presents it in ``auth``. Construction validates every field and raises
    ProtocolError (``bad_field``) naming the field.
    """

    KIND: ClassVar[Kind] = "user_grant"
    _FIELDS: ClassVar[frozenset[str]] = frozenset(
        {
            "v",
            "kind",
            "session_id",
            "vehicle_id",
            "user",
            "role",
            "allowed_commands",
            "iat",
            "exp",
            "nonce",
        }
    )

    session_id: str
    vehicle_id: str
    user: str
    role: str
    #: Command names this user may send; a viewer normally gets an empty tuple.
    allowed_commands: tuple[str, ...]
    issued_at: float
    expires_at: float
    nonce: str = field(default_factory=new_nonce)

    def __post_init__(self) -> None:
        _check_id(self.session_id, "session_id")
        _check_id(self.vehicle_id, "vehicle_id")
        _check_id(self.user, "user")
        _check_role(self.role, "role")
        object.__setattr__(
            self,
            "allowed_commands",
            _check_commands_tuple(self.allowed_commands, "allowed_commands"),
        )
        _check_times(self.issued_at, self.expires_at)
        _check_id(self.nonce, "nonce")

    def to_payload(self) -> dict[str, Any]:
        """Return the document payload (with ``v`` and ``kind``) ready for signing."""
        return {
            "v": PROTOCOL_VERSION,
            "kind": self.KIND,
            "session_id": self.session_id,
            "vehicle_id": self.vehicle_id,
            "user": self.user,
            "role": self.role,
            "allowed_commands": list(self.allowed_commands),
            "iat": self.issued_at,
            "exp": self.expires_at,
            "nonce": self.nonce,
        }

    @classmethod
    def from_payload(cls, payload: Any) -> UserGrant:
        """Build a UserGrant from a (verified) payload.

        Returns the grant. Raises ProtocolError naming the field for a missing, unknown or
        bad field, ``bad_version`` for another version and ``wrong_kind`` for a task.
        """
        if not isinstance(payload, Mapping):
            raise ProtocolError("bad_field", "document payload must be an object")
        _check_keys(payload, cls._FIELDS, "")
        _require(
            payload,
            (
                "v",
                "kind",
                "session_id",
                "vehicle_id",
                "user",
                "role",
                "allowed_commands",
                "iat",
                "exp",
                "nonce",
            ),
        )
        _check_version(payload["v"], "v")
        if payload["kind"] != cls.KIND:
            raise ProtocolError("wrong_kind", f"document kind must be {cls.KIND}", field="kind")
        return cls(
            session_id=payload["session_id"],
            vehicle_id=payload["vehicle_id"],
            user=payload["user"],
            role=payload["role"],
            allowed_commands=_check_commands_tuple(payload["allowed_commands"], "allowed_commands"),
            issued_at=payload["iat"],
            expires_at=payload["exp"],
            nonce=payload["nonce"],
        )

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return this grant as a signed token (see :func:`sign_document`)."""
        return sign_document(self.to_payload(), private_key)

    @classmethod
    def verify(
        cls,
        token: str,
        public_key: Ed25519PublicKey,
        *,
        vehicle_id: str,
        now: float | None = None,
        replay_guard: ReplayGuard | None = None,
    ) -> UserGrant:
        """Verify a grant presented to the agent whose id is ``vehicle_id``.

        Same order and errors as :meth:`VehicleTask.verify`. With ``replay_guard`` the
        grant's nonce is consumed: a grant opens one connection, a reconnect needs a fresh
        grant from the platform.
        """
        payload = _verify_common(token, public_key, cls.KIND, vehicle_id, now)
        grant = cls.from_payload(payload)
        _check_target(
            grant.vehicle_id, vehicle_id, grant.nonce, grant.expires_at, now, replay_guard
        )
        return grant


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
        _check_id(nonce, "nonce")
        _check_timestamp(expires_at, "exp")
        current = time.time() if now is None else now
        self._prune(current)
        if nonce in self._forget_at:
            raise ReplayError("document nonce was already used")
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
