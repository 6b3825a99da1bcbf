"""Wire protocol shared by the IoUV platform and the vehicle agent.

This module is the only code the Django platform and the vehicle agent have in common, so it
imports nothing but the standard library, msgspec, ``cryptography``, PyJWT and the
missions' specs (``agents/missions/<name>/spec.py``, msgspec only: the vehicle task's
``mission`` is their tagged union): the agent runs on small companion computers without
Django.

It provides:

* signed documents (the *vehicle task* and the *user grant*) as JWTs (EdDSA), signed
  with the platform's Ed25519 private key and verified offline by the agent, which holds
  only the public keys (:class:`KeySet`, from PEM or a JWKS);
* :class:`ReplayGuard`, which makes each document id (``jti``) single-use;
* parsing and validation of the JSON messages of the four WebSocket channels;
* validation of command arguments against a vehicle's declared command vocabulary.

Every refusal is a :class:`ProtocolError` (or a subclass) carrying a short machine ``code``
and a message naming the offending field, so callers can answer the peer with
:func:`error_message` without inspecting exception types. ``docs/protocol.md`` describes the
protocol for people integrating vehicles and writing clients.
"""

from agents.protocol.base import (
    ARG_TYPES,
    CHANNELS,
    CLOCK_SKEW_S,
    DEFAULT_LINK_LOSS_TIMEOUT_MS,
    FAILSAFE_ACTIONS,
    KINDS,
    MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    REPLAY_GUARD_MAX_ENTRIES,
    ROLES,
    Channel,
    ExpiredError,
    Kind,
    ProtocolError,
    ReplayError,
    SignatureError,
    WrongTargetError,
)
from agents.protocol.documents import (
    ISSUER,
    TOKEN_TYPES,
    Limits,
    PublicKeys,
    ReplayGuard,
    SfuPublish,
    UnknownKeyError,
    UserGrant,
    VehicleTask,
    claimed_session,
    new_nonce,
)
from agents.protocol.keys import (
    KeySet,
    generate_keypair,
    jwks_from_keys,
    key_thumbprint,
    load_private_key,
    load_public_key,
    load_public_keys,
    public_key_pem,
)
from agents.protocol.messages import (
    MESSAGE_TYPES,
    encode_message,
    error_message,
    parse_message,
    validate_command_args,
)

__all__ = [
    "ARG_TYPES",
    "CHANNELS",
    "CLOCK_SKEW_S",
    "DEFAULT_LINK_LOSS_TIMEOUT_MS",
    "FAILSAFE_ACTIONS",
    "ISSUER",
    "KINDS",
    "MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "REPLAY_GUARD_MAX_ENTRIES",
    "ROLES",
    "TOKEN_TYPES",
    "Channel",
    "ExpiredError",
    "KeySet",
    "Kind",
    "Limits",
    "ProtocolError",
    "PublicKeys",
    "ReplayError",
    "ReplayGuard",
    "SfuPublish",
    "SignatureError",
    "UnknownKeyError",
    "UserGrant",
    "VehicleTask",
    "WrongTargetError",
    "claimed_session",
    "encode_message",
    "error_message",
    "generate_keypair",
    "jwks_from_keys",
    "key_thumbprint",
    "load_private_key",
    "load_public_key",
    "load_public_keys",
    "new_nonce",
    "parse_message",
    "public_key_pem",
    "validate_command_args",
]
