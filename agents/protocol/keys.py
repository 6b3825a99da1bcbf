"""The platform's Ed25519 keys: PEM loading, JWK thumbprints, JWKS and the verifier's key set.

The platform signs with one private key; verifiers (agents, the platform's own relay) hold
a :class:`KeySet` of public keys, each named by its key id (``kid``). During a key rotation
the set holds two keys, so documents signed before and after the switch both verify. Key
ids are RFC 7638 JWK thumbprints, so the same key always gets the same id wherever it is
loaded from (a PEM file, a JWKS document, the platform's ``/.well-known/jwks.json``).
"""

from __future__ import annotations

import binascii
import hashlib
import json
from collections.abc import Iterable, Iterator, Mapping
from typing import Any, Final

from cryptography.exceptions import UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)
from jwt.algorithms import OKPAlgorithm
from jwt.exceptions import InvalidKeyError
from jwt.utils import base64url_encode

from agents.protocol.base import ProtocolError

#: The only JWS algorithm the platform signs with and verifiers accept (RFC 8037).
ALGORITHM: Final = "EdDSA"

#: A JWKS with more keys than this is a mistake (a rotation needs two).
MAX_JWKS_KEYS: Final = 16

# ``alg`` values a JWK may declare for an Ed25519 key: RFC 8037's EdDSA and RFC 9864's
# fully specified Ed25519 (what newer publishers write).
_JWK_ALGS: Final = frozenset({"EdDSA", "Ed25519"})


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
    return private_pem, public_key_pem(private_key.public_key())


def public_key_pem(key: Ed25519PublicKey) -> str:
    """``key`` as SubjectPublicKeyInfo PEM text. Raises nothing."""
    return key.public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    ).decode("ascii")


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


def load_public_keys(text: str) -> list[Ed25519PublicKey]:
    """Load every PEM public key in ``text`` (several PEM blocks may follow each other).

    Returns the keys in order (empty for blank text). Raises ProtocolError ``bad_key`` for
    a block that is not an Ed25519 public key.
    """
    end = "-----END PUBLIC KEY-----"
    blocks = [b + end for b in text.split(end) if b.strip()]
    return [load_public_key(block) for block in blocks]


def key_thumbprint(key: Ed25519PublicKey | Ed25519PrivateKey) -> str:
    """The RFC 7638 JWK thumbprint of ``key``'s public half: base64url(SHA-256).

    Used as the ``kid`` of every token and JWKS entry. Raises nothing.
    """
    public = key.public_key() if isinstance(key, Ed25519PrivateKey) else key
    x = base64url_encode(public.public_bytes_raw()).decode("ascii")
    # RFC 7638 §3.2: the required members only, lexicographic order, no whitespace.
    members = json.dumps({"crv": "Ed25519", "kty": "OKP", "x": x}, separators=(",", ":"))
    return base64url_encode(hashlib.sha256(members.encode("ascii")).digest()).decode("ascii")


def public_jwk(key: Ed25519PublicKey) -> dict[str, Any]:
    """``key`` as a public JWK (RFC 8037) with ``kid`` (its thumbprint), ``alg`` and ``use``."""
    jwk = dict(OKPAlgorithm.to_jwk(key, as_dict=True))
    jwk.update({"kid": key_thumbprint(key), "alg": ALGORITHM, "use": "sig"})
    return jwk


def jwks_from_keys(keys: Iterable[Ed25519PublicKey]) -> dict[str, Any]:
    """A JWK Set (RFC 7517 §5) listing ``keys`` in order, each with its thumbprint ``kid``."""
    return {"keys": [public_jwk(key) for key in keys]}


def _bad_key(index: int, problem: str) -> ProtocolError:
    return ProtocolError("bad_key", f"JWKS key {index} {problem}", field=f"keys[{index}]")


def _key_from_jwk(jwk: Any, index: int) -> tuple[str, Ed25519PublicKey]:
    """One JWKS entry as ``(kid, key)``; refuses anything but a public Ed25519 signing key."""
    if not isinstance(jwk, Mapping):
        raise _bad_key(index, "must be an object")
    if jwk.get("kty") != "OKP" or jwk.get("crv") != "Ed25519":
        raise _bad_key(index, "must be an OKP key on curve Ed25519")
    if "d" in jwk:
        # A published private key is compromised: refuse it loudly rather than ignore it.
        raise _bad_key(index, "holds private key material")
    if jwk.get("use", "sig") != "sig":
        raise _bad_key(index, "is not a signature key (use)")
    if jwk.get("alg", ALGORITHM) not in _JWK_ALGS:
        raise _bad_key(index, f"declares alg {jwk.get('alg')!r}, not EdDSA")
    if not isinstance(jwk.get("x"), str):
        raise _bad_key(index, "has no 'x'")
    try:
        key = OKPAlgorithm.from_jwk(dict(jwk))
    except (InvalidKeyError, ValueError, TypeError, binascii.Error) as exc:
        raise _bad_key(index, f"cannot be loaded: {exc}") from None
    if not isinstance(key, Ed25519PublicKey):
        raise _bad_key(index, "is not an Ed25519 public key")
    kid = jwk.get("kid", key_thumbprint(key))
    if not isinstance(kid, str) or not kid:
        raise _bad_key(index, "has an empty or non-text 'kid'")
    return kid, key


class KeySet:
    """The platform public keys a verifier trusts, by key id. Immutable.

    Build it with :meth:`from_keys`, :meth:`from_pem` or :meth:`from_jwks`; every
    constructor refuses an empty set with ProtocolError ``bad_key``. A token names its key
    in the ``kid`` header; :meth:`select` finds it.
    """

    def __init__(self, keys: Mapping[str, Ed25519PublicKey]) -> None:
        if not keys:
            raise ProtocolError("bad_key", "a key set needs at least one key")
        self._keys: dict[str, Ed25519PublicKey] = dict(keys)

    @classmethod
    def from_keys(cls, keys: Iterable[Ed25519PublicKey]) -> KeySet:
        """The set of ``keys``, each named by its thumbprint."""
        return cls({key_thumbprint(key): key for key in keys})

    @classmethod
    def from_pem(cls, *pems: str) -> KeySet:
        """The set of the PEM public keys in ``pems`` (each text may hold several blocks).

        Raises ProtocolError ``bad_key`` for a bad block or when there is no key at all.
        """
        keys = [key for pem in pems for key in load_public_keys(pem)]
        return cls.from_keys(keys)

    @classmethod
    def from_jwks(cls, jwks: Any) -> KeySet:
        """The set of the keys of a JWK Set document (a parsed JSON object).

        Every entry must be a public Ed25519 key (``kty`` OKP, ``crv`` Ed25519, no ``d``,
        ``use`` sig and ``alg`` EdDSA/Ed25519 when given); one bad entry refuses the whole
        set, so a misconfiguration is noticed instead of half-applied. Entries without a
        ``kid`` are named by their thumbprint. Raises ProtocolError ``bad_key``.
        """
        if not isinstance(jwks, Mapping) or not isinstance(jwks.get("keys"), list):
            raise ProtocolError("bad_key", "a JWKS must be an object with a 'keys' list")
        entries = jwks["keys"]
        if not 0 < len(entries) <= MAX_JWKS_KEYS:
            raise ProtocolError("bad_key", f"a JWKS must hold 1 to {MAX_JWKS_KEYS} keys")
        keys: dict[str, Ed25519PublicKey] = {}
        for index, entry in enumerate(entries):
            kid, key = _key_from_jwk(entry, index)
            if kid in keys:
                raise _bad_key(index, f"repeats kid {kid!r}")
            keys[kid] = key
        return cls(keys)

    def union(self, other: KeySet) -> KeySet:
        """The keys of both sets (``other``'s win on a repeated kid)."""
        return KeySet({**self._keys, **other._keys})

    def select(self, kid: str | None) -> Ed25519PublicKey | None:
        """The key named ``kid``; without a kid, the only key (None when there are several,
        since guessing would let a token pick its own verifier). None if unknown."""
        if kid is None:
            return next(iter(self._keys.values())) if len(self._keys) == 1 else None
        return self._keys.get(kid)

    def to_jwks(self) -> dict[str, Any]:
        """The set as a JWKS document (kids as held)."""
        keys = []
        for kid, key in self._keys.items():
            jwk = public_jwk(key)
            jwk["kid"] = kid
            keys.append(jwk)
        return {"keys": keys}

    @property
    def kids(self) -> list[str]:
        """The key ids, in the order the keys were given."""
        return list(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys)

    def __contains__(self, kid: object) -> bool:
        return kid in self._keys

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, KeySet):
            return NotImplemented
        return {k: v.public_bytes_raw() for k, v in self._keys.items()} == {
            k: v.public_bytes_raw() for k, v in other._keys.items()
        }

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"KeySet({self.kids!r})"
