"""Signed documents (vehicle task, user grant) as JWTs, and replay protection.

A document is a compact JWS (RFC 7515) JWT (RFC 7519) signed by the platform with EdDSA
over Ed25519 (RFC 8037) through PyJWT; this module writes no signature encoding of its
own. The header names the signing key (``kid``, an RFC 7638 thumbprint) and the document's
purpose by explicit typing (RFC 8725 §3.11): ``typ`` is ``iouv-task+jwt`` or
``iouv-grant+jwt``, and one is never accepted as the other. Registered claims carry the
issuer, the vehicle (``aud``), the user (``sub``), the validity window (``iat``, ``nbf``,
``exp``) and a single-use id (``jti``); project claims carry the rest.

:class:`Limits` and the documents are frozen :class:`msgspec.Struct` types whose fields
travel under their claim names. msgspec checks every claim, whether it comes from a
verified token or from code that builds a document.
"""

from __future__ import annotations

import heapq
import json
import math
import re
import secrets
import sys
import time
from collections.abc import Mapping
from contextvars import ContextVar
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Final, Self, TypeAlias, TypeVar

import jwt
import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from jwt.utils import base64url_decode, base64url_encode
from msgspec import Meta, field

from agents.missions.registry import mission_union
from agents.missions.spec import MissionSpec as MissionSpecBase
from agents.missions.spec import spec_decoding
from agents.protocol.base import (
    _LINK_LOSS_RANGE_MS,
    _MAX_TOKEN_CHARS,
    CLOCK_SKEW_S,
    DEFAULT_LINK_LOSS_TIMEOUT_MS,
    PROTOCOL_VERSION,
    REPLAY_GUARD_MAX_ENTRIES,
    ExpiredError,
    Kind,
    ProtocolError,
    ReplayError,
    SignatureError,
    WrongTargetError,
    _bad,
)
from agents.protocol.keys import ALGORITHM, KeySet, key_thumbprint
from agents.protocol.messages import Id, Latitude, Longitude, Version, _invalid, _protocol_error

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
# Field types and checking
# --------------------------------------------------------------------------------------

# Unix seconds: anything beyond this is a bug, and it keeps float conversion from overflowing.
_MAX_TIMESTAMP: Final = 1e12
Timestamp = Annotated[float, Meta(ge=-_MAX_TIMESTAMP, le=_MAX_TIMESTAMP)]
# An int stays an int. msgspec lets infinity through a float; the finite bound does not.
PositiveNumber = Annotated[int, Meta(gt=0)] | Annotated[float, Meta(gt=0, le=sys.float_info.max)]
PositiveInt = Annotated[int, Meta(gt=0)]
LinkLossMs = Annotated[int, Meta(ge=_LINK_LOSS_RANGE_MS[0], le=_LINK_LOSS_RANGE_MS[1])]
if TYPE_CHECKING:  # callers hold these as plain text (a database column)
    FailsafeAction = str
    Role = str
else:  # msgspec refuses any other value
    from agents.protocol.messages import FailsafeAction, Role

_T = TypeVar("_T")

if TYPE_CHECKING:
    from agents.missions.spec import MissionSpec
else:
    # The tagged union of the installed missions' specs (agents.missions.registry),
    # resolved by msgspec from this module's globals.
    MissionSpec = mission_union()

# True while msgspec builds a struct from values it has checked (see _Checked).
_CONVERTING: Final[ContextVar[bool]] = ContextVar("iouv_documents_converting", default=False)


def _convert(data: Any, type_: type[_T]) -> _T:
    """``data`` checked by msgspec and converted to ``type_``.

    Raises ProtocolError as messages are refused (``bad_field`` naming the field's path,
    ``bad_version`` for ``v``); an unknown field is refused naming it.
    """
    token = _CONVERTING.set(True)
    try:
        with spec_decoding():  # a mission spec inside is being checked too
            return msgspec.convert(data, type_)
    except msgspec.ValidationError as exc:
        raise _protocol_error(exc) from None
    finally:
        _CONVERTING.reset(token)


def _plain(obj: msgspec.Struct) -> dict[str, Any]:
    """``obj`` as plain JSON data (lists, not tuples) under its fields' encoded names."""
    data: dict[str, Any] = json.loads(json.dumps(msgspec.to_builtins(obj)))
    return data


class _Checked(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """A struct whose constructor checks its fields as decoding does.

    msgspec checks types and ``Meta`` constraints only when it decodes or converts, so a
    struct constructed in code is converted into a checked copy whose (normalised) values
    it takes. Either way a refusal is a ProtocolError naming the field as it travels, and
    an invalid struct cannot exist.

    Unknown fields are refused: signed documents fail closed, since a field this end does
    not understand may be a limit it would fail to enforce.
    """

    def __post_init__(self) -> None:
        if _CONVERTING.get():  # msgspec built this from checked values
            self._check()
            return
        checked = self._checked_copy()
        for name in self.__struct_fields__:
            msgspec.structs.force_setattr(self, name, getattr(checked, name))

    def _fields(self) -> dict[str, Any]:
        # Not msgspec.structs.fields(): it resolves the type hints on every call.
        names = zip(self.__struct_encode_fields__, self.__struct_fields__, strict=True)
        return {claim: getattr(self, name) for claim, name in names}

    def _checked_copy(self) -> _Checked:
        return _convert(self._fields(), type(self))

    def _check(self) -> None:
        """Check across fields and normalise, once each field has been checked.

        Raises ValueError (:func:`_invalid`), which msgspec reports at this struct's path.
        """


# --------------------------------------------------------------------------------------
# Limits
# --------------------------------------------------------------------------------------


class Limits(_Checked, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Safety limits the agent enforces for one session. ``None`` means "no limit".

    Construction validates every field and raises ProtocolError (``bad_field``, naming
    ``limits.<field>``) on a bad value, so an invalid Limits object cannot exist.
    """

    max_altitude_m: PositiveNumber | None = None
    #: (latitude, longitude) in degrees; set together with geofence_radius_m.
    geofence_center: tuple[Latitude, Longitude] | None = None
    geofence_radius_m: PositiveNumber | None = None
    max_speed_mps: PositiveNumber | None = None
    #: Silence from the controlling user after which the agent runs failsafe_action.
    link_loss_timeout_ms: LinkLossMs = DEFAULT_LINK_LOSS_TIMEOUT_MS
    failsafe_action: FailsafeAction = "stop"
    #: Past this round-trip latency the agent lowers the allowed speed.
    latency_soft_ms: PositiveInt | None = None
    #: Past this round-trip latency only stop / land / return_to_home are accepted.
    latency_hard_ms: PositiveInt | None = None
    session_time_limit_s: PositiveInt | None = None

    def _check(self) -> None:
        if (self.geofence_center is None) != (self.geofence_radius_m is None):
            raise _invalid(
                "geofence_center",
                "and geofence_radius_m must be set together (a fence needs both)",
            )
        soft, hard = self.latency_soft_ms, self.latency_hard_ms
        if soft is not None and hard is not None and soft > hard:
            raise _invalid("latency_soft_ms", "must not exceed latency_hard_ms")

    def _checked_copy(self) -> Limits:
        return self.from_payload(self._fields())

    def to_payload(self) -> dict[str, Any]:
        """Return the JSON-ready dict (every field present, ``None`` as null)."""
        return _plain(self)

    @classmethod
    def from_payload(cls, payload: Any) -> Limits:
        """Build Limits from a payload dict; absent fields take their defaults.

        Returns the Limits. Raises ProtocolError ``bad_field`` naming ``limits.<field>``
        for a non-object, an unknown field, or a bad value.
        """
        return _convert({"limits": payload}, _InTask).limits


# --------------------------------------------------------------------------------------
# Publishing to the SFU
# --------------------------------------------------------------------------------------

#: Janus ids travel as JSON numbers: they stay below 2**53 so a browser reads them exactly.
JanusId = Annotated[int, Meta(ge=1, lt=2**53)]
JanusToken = Annotated[str, Meta(min_length=1, max_length=500)]


class SfuPublish(_Checked, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Where the vehicle sends its one copy of the video for spectators: a room of the
    platform's SFU (Janus VideoRoom, docs/video.md "The SFU").

    ``url``: Janus's WebSocket API; ``token``: a Janus core token (``token_auth``) valid
    for the VideoRoom plugin; ``room``, ``feed``: the session's room and the publisher id
    spectators subscribe to; ``publish_token``: the room's ``allowed`` token that lets
    this vehicle, and no spectator, publish; ``pin``: the room's pin.
    """

    url: Annotated[str, Meta(pattern=r"^wss?://", max_length=500)]
    token: JanusToken
    room: JanusId
    feed: JanusId
    publish_token: JanusToken
    pin: JanusToken


class _InTask(msgspec.Struct):
    """Limits where they travel, so that a refusal names ``limits.<field>``."""

    limits: Limits


# --------------------------------------------------------------------------------------
# Documents
# --------------------------------------------------------------------------------------


class _Window(msgspec.Struct):
    """A document's version and validity window, which verification checks first."""

    v: Version
    exp: Timestamp
    nbf: Timestamp
    iat: Timestamp


class _Document(_Checked, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What VehicleTask and UserGrant share: registered claims, signing, verification."""

    KIND: ClassVar[Kind]
    #: Every claim the document may carry; any other is refused (fail closed).
    CLAIMS: ClassVar[frozenset[str]]

    session_id: Id
    vehicle_id: Id = field(name="aud")
    user: Id = field(name="sub")
    #: Command names (from the vehicle's vocabulary) that may be sent.
    allowed_commands: tuple[Id, ...]
    issued_at: Timestamp = field(name="iat")
    expires_at: Timestamp = field(name="exp")
    nonce: Id = field(default_factory=new_nonce, name="jti")
    issuer: Id = field(default=ISSUER, name="iss")

    def _check(self) -> None:
        if self.expires_at < self.issued_at:
            raise _invalid("exp", "must not be earlier than iat")
        # JWT verifiers commonly compare ``iat`` with their clock in whole seconds and no
        # leeway (joserfc does): a fractional ``iat`` would be "issued in the future" for
        # up to a second. Flooring moves ``iat`` earlier and ``exp`` sooner, never
        # widening validity.
        msgspec.structs.force_setattr(self, "issued_at", math.floor(self.issued_at))
        msgspec.structs.force_setattr(self, "expires_at", math.floor(self.expires_at))

    def to_payload(self) -> dict[str, Any]:
        """Return the JWT claims (registered, ``v`` and the document's own) ready for
        signing."""
        # Valid from its issue: a document is never post-dated.
        return {**_plain(self), "nbf": self.issued_at, "v": PROTOCOL_VERSION}

    @classmethod
    def from_payload(cls, payload: Any) -> Self:
        """Build the document from (verified) claims.

        Returns the document. Raises ProtocolError naming the claim for a missing, unknown
        or bad one, ``bad_version`` for another version.
        """
        if not isinstance(payload, Mapping):
            raise ProtocolError("bad_field", "document claims must be an object")
        for claim in payload:  # named here: the translation reserves some paths ("type")
            if claim not in cls.CLAIMS:
                raise _bad(str(claim), "is not known")
        # Required even where the constructor has a default (``iss``, ``jti``).
        for claim in (*_REQUIRED, "v"):
            if claim not in payload:
                raise _bad(claim, "is missing")
        _convert({name: payload[name] for name in _Window.__struct_fields__}, _Window)
        return _convert({k: v for k, v in payload.items() if k not in ("nbf", "v")}, cls)

    def sign(self, private_key: Ed25519PrivateKey) -> str:
        """Return the document as a compact JWT signed with ``private_key`` (EdDSA), its
        ``kid`` the key's thumbprint and its ``typ`` the kind's (:data:`TOKEN_TYPES`)."""
        headers = {"kid": key_thumbprint(private_key), "typ": TOKEN_TYPES[self.KIND]}
        return jwt.encode(self.to_payload(), private_key, algorithm=ALGORITHM, headers=headers)

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
        max_lifetime_s: float | None = None,
    ) -> Self:
        """Verify a token of this kind on the agent whose id is ``vehicle_id``.

        ``keys`` is the platform key, or a :class:`KeySet` from which the token's ``kid``
        picks one. ``now`` (Unix seconds, default ``time.time()``) is the verifier's clock;
        ``CLOCK_SKEW_S`` is tolerated on ``exp``, ``nbf`` and ``iat``. ``max_lifetime_s``:
        a document valid longer than this (``exp - iat``) is refused, however it is
        signed: a leaked one would open the vehicle for as long as it says, and its
        ``jti`` would have to be remembered as long.

        Order: shape, key, signature, required claims, ``iss``, ``aud``, ``typ``, ``v``,
        times, every claim's value, the lifetime, then, if ``replay_guard`` is given, the
        ``jti``.

        Returns the document. Raises only ProtocolError subclasses: SignatureError
        (``bad_signature``; UnknownKeyError ``unknown_key``), ExpiredError (``expired``),
        WrongTargetError (``wrong_vehicle``), ReplayError (``replayed``) or ProtocolError
        (``bad_token``, ``wrong_issuer``, ``wrong_kind``, ``bad_version``,
        ``not_yet_valid``, ``bad_field``, ``lifetime_too_long``); ValueError only for an
        empty ``vehicle_id``.
        """
        claims = _decode(token, keys, kind=cls.KIND, vehicle_id=vehicle_id, issuer=issuer, now=now)
        doc = cls.from_payload(claims)
        if doc.vehicle_id != vehicle_id:  # PyJWT checked ``aud`` already; a second lock
            err = WrongTargetError(
                f"document is for vehicle {doc.vehicle_id!r}, this is {vehicle_id!r}"
            )
            raise _with_field(err, "aud")
        lifetime = doc.expires_at - doc.issued_at
        if max_lifetime_s is not None and lifetime > max_lifetime_s:
            raise ProtocolError(
                "lifetime_too_long",
                f"document is valid for {lifetime:g} s; this vehicle accepts at most "
                f"{max_lifetime_s:g} s",
                field="exp",
            )
        # Replay last: a document refused for another reason must not burn its id.
        if replay_guard is not None:
            replay_guard.check_and_remember(doc.nonce, doc.expires_at, now=now)
        return doc


def _claims_of(cls: type[_Document]) -> frozenset[str]:
    return frozenset(f.encode_name for f in msgspec.structs.fields(cls)) | {"nbf", "v"}


class VehicleTask(_Document, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What the platform asks one vehicle to do for one session (signed, pushed on uplink).

    Construction validates every field and raises ProtocolError (``bad_field``) naming the
    claim it travels as. ``issued_at``/``expires_at`` are Unix seconds, floored to whole
    seconds, and travel as ``iat`` (and ``nbf``)/``exp``; ``vehicle_id`` as ``aud``,
    ``user`` as ``sub``, ``nonce`` as ``jti`` and ``issuer`` as ``iss``.
    """

    KIND: ClassVar[Kind] = "vehicle_task"

    limits: Limits
    #: The autonomous mission the vehicle flies for this session, one of the installed
    #: missions' specs (agents/missions/<name>/spec.py), tagged by its ``kind``.
    mission: MissionSpec | None = None
    #: Publish the camera to the platform's SFU for spectators (absent: no SFU, or a
    #: vehicle without a camera; only sent to agents whose profile says ``sfu``).
    sfu: SfuPublish | None = None

    def to_payload(self) -> dict[str, Any]:
        payload = super().to_payload()
        if payload.get("sfu") is None:
            # Absent rather than null: agents from before the SFU refuse any claim they
            # do not know (signed documents fail closed).
            del payload["sfu"]
        return payload

    def __post_init__(self) -> None:
        # Converting would turn a dict into Limits (or a mission spec); code must hand
        # over checked ones.
        if not isinstance(self.limits, Limits):
            raise _bad("limits", "must be a Limits object")
        if self.mission is not None and not isinstance(self.mission, MissionSpecBase):
            raise _bad("mission", "must be a mission spec (agents/missions/<name>/spec.py)")
        super().__post_init__()


VehicleTask.CLAIMS = _claims_of(VehicleTask)


class UserGrant(_Document, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Permission for one user to connect to one vehicle's control socket (signed).

    The browser presents it in ``auth``. Construction validates every field and raises
    ProtocolError (``bad_field``) naming the claim (see :class:`VehicleTask`). Verified
    with a ``replay_guard``, a grant's ``jti`` is consumed: a grant opens one connection,
    a reconnect needs a fresh grant from the platform. A viewer normally gets no
    ``allowed_commands``.
    """

    KIND: ClassVar[Kind] = "user_grant"

    role: Role


UserGrant.CLAIMS = _claims_of(UserGrant)


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
# Verification
# --------------------------------------------------------------------------------------


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
    window = _convert({name: claims[name] for name in _Window.__struct_fields__}, _Window)
    current = time.time() if now is None else now
    if current - CLOCK_SKEW_S > window.exp:
        raise ExpiredError(f"document expired at {window.exp} (now {current:.3f})")
    starts = max(window.nbf, window.iat)
    if starts > current + CLOCK_SKEW_S:
        raise ProtocolError(
            "not_yet_valid", f"document is valid from {starts} (now {current:.3f})", field="nbf"
        )
    return claims


# --------------------------------------------------------------------------------------
# Replay protection
# --------------------------------------------------------------------------------------


class _Use(msgspec.Struct):
    """What a ReplayGuard is told of a document."""

    jti: Id
    exp: Timestamp


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
        use = _convert({"jti": nonce, "exp": expires_at}, _Use)
        current = time.time() if now is None else now
        self._prune(current)
        if use.jti in self._forget_at:
            raise _with_field(ReplayError("document id (jti) was already used"), "jti")
        while len(self._forget_at) >= self._max_entries:
            del self._forget_at[next(iter(self._forget_at))]
        forget_at = use.exp + CLOCK_SKEW_S
        self._forget_at[use.jti] = forget_at
        heapq.heappush(self._heap, (forget_at, use.jti))
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


# msgspec works out how to convert to a struct type on the type's first use and keeps
# that on the class. Done here, under the import lock, it never happens on two request
# threads at once (a platform process under load once died of a segfault in msgspec's
# extension on its first requests; this takes one candidate cause away).
for _type in (Limits, SfuPublish, VehicleTask, UserGrant):
    msgspec.json.Decoder(_type)
