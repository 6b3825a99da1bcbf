"""What every mission spec is: a frozen, tagged msgspec struct checked like a signed
document, and the field types the specs share.

A spec travels in the vehicle task's ``mission`` claim as a JSON object whose ``kind``
names the mission (the struct's ``tag``). msgspec checks types and ``Meta`` constraints
only when it decodes, so a spec built in code (the platform building a mission) is
checked on construction by a round trip through the decoder: an invalid spec cannot be
made, wherever it comes from. Cross-field rules go in :meth:`MissionSpec.check`.

Imports nothing but msgspec and the standard library: :mod:`agents.protocol` (and so
the platform) imports every spec.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from contextvars import ContextVar
from typing import Annotated, Any, Final, TypeAlias

import msgspec
from msgspec import Meta

#: The field of the mission object that names its kind (the structs' ``tag_field``).
TAG_FIELD: Final = "kind"

MAX_ALTITUDE_M: Final = 500
MAX_SPEED_MPS: Final = 50

MissionId: TypeAlias = Annotated[str, Meta(min_length=1, max_length=100)]
Latitude: TypeAlias = Annotated[float, Meta(ge=-90, le=90)]
Longitude: TypeAlias = Annotated[float, Meta(ge=-180, le=180)]
#: ``[lat, lon]`` in degrees.
LatLon: TypeAlias = tuple[Latitude, Longitude]
#: A cruise altitude above the take-off point.
Altitude: TypeAlias = Annotated[float, Meta(ge=1, le=MAX_ALTITUDE_M)]
#: A low altitude over a point (loading, dropping).
LowAltitude: TypeAlias = Annotated[float, Meta(ge=0.5, le=MAX_ALTITUDE_M)]
#: Capped later at the vehicle's declared top speed.
Speed: TypeAlias = Annotated[float, Meta(ge=0.1, le=MAX_SPEED_MPS)]


# True while msgspec builds specs from data it is checking (see MissionSpec).
_DECODING: Final[ContextVar[bool]] = ContextVar("iouv_mission_decoding", default=False)


class MissionError(ValueError):
    """A mission is malformed; the message names the field (``mission.<field>: ...``)."""


@contextlib.contextmanager
def spec_decoding() -> Iterator[None]:
    """Within: msgspec is decoding, so specs check only across fields (the decoder
    checks the rest). :mod:`agents.protocol` decodes documents within it."""
    token = _DECODING.set(True)
    try:
        yield
    finally:
        _DECODING.reset(token)


def spec_convert(data: Any, type_: Any) -> Any:
    """``data`` (JSON-like) checked and converted to ``type_`` (a spec or a union of
    specs). Raises MissionError naming the field."""
    with spec_decoding():
        try:
            return msgspec.convert(data, type_)
        except msgspec.ValidationError as exc:
            raise MissionError(_named(str(exc))) from None


_WHERE: Final = re.compile(r"^(?P<problem>.*?)(?: - at `\$(?P<path>[^`]*)`)?$", re.S)
_MISSING: Final = re.compile(r"^Object missing required field `(?P<name>[^`]*)`$")
_UNKNOWN: Final = re.compile(r"^Object contains unknown field `(?P<name>.*)`$", re.S)
_MARKED: Final = re.compile(r"^<(?P<path>[^>]*)> (?P<problem>.*)$", re.S)


def spec_invalid(field: str, problem: str) -> ValueError:
    """The refusal :meth:`MissionSpec.check` raises for ``field`` (the convention of
    agents.protocol's ``_invalid``, so a refused task names ``mission.<field>`` too)."""
    return ValueError(f"<{field}> {problem}")


def _named(text: str) -> str:
    """msgspec's "problem - at `$.a.b`" as "mission.a.b: problem", a missing or unknown
    field and a :func:`spec_invalid` refusal named by their own path (as agents.protocol
    names the fields of a refused document)."""
    where = _WHERE.match(text)
    assert where is not None  # the pattern matches any text
    problem, path = where["problem"], where["path"] or ""
    if missing := _MISSING.match(problem):
        path, problem = f"{path}.{missing['name']}", "is missing"
    elif unknown := _UNKNOWN.match(problem):
        path, problem = f"{path}.{unknown['name']}", "is not known"
    elif marked := _MARKED.match(problem):
        path, problem = f"{path}.{marked['path']}", marked["problem"]
    return f"mission{path}: {problem}"


class MissionSpec(
    msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag_field=TAG_FIELD
):
    """The base of every mission's spec. A subclass sets ``tag=...`` (its ``kind``) and
    declares its fields with constraints; ``check`` adds rules across fields.

    Unknown fields are refused: missions fail closed, like the documents that carry them.
    Construction raises MissionError naming the field.
    """

    #: The agent keeps one running mission per id and never repeats a finished one.
    id: MissionId

    def __post_init__(self) -> None:
        if _DECODING.get():
            self.check()
            return
        # Built in code: msgspec has checked nothing yet; take a decoded copy's values.
        checked = spec_convert(msgspec.to_builtins(self), type(self))
        for name in self.__struct_fields__:
            msgspec.structs.force_setattr(self, name, getattr(checked, name))

    def check(self) -> None:
        """Rules across fields, once each field is checked. Raises
        :func:`spec_invalid` naming the field."""

    @classmethod
    def mission_kind(cls) -> str:
        """The mission's ``kind`` on the wire (the ``tag`` the subclass declares)."""
        return str(cls.__struct_config__.tag)

    def to_payload(self) -> dict[str, Any]:
        """The spec as the JSON object that travels (``kind`` first)."""
        data: dict[str, Any] = msgspec.json.decode(msgspec.json.encode(self))
        return data
