"""The missions this installation has, by folder and by ``kind``.

A mission is a package ``agents/missions/<name>/`` whose ``__init__.py`` declares
``MISSION = Mission(...)``. Adding one is adding its folder: the vehicle task's
``mission`` union (:func:`mission_union`), the published schema and the agent's
:class:`~agents.missions.control.MissionControl` find it here.

A mission's ``__init__.py`` and ``spec.py`` stay light (msgspec only): its runner, and
whatever only it needs (the search's thermal camera and numpy), are imported by the
callables of its declaration, when an agent flies it or opens its sensor, never when the
platform builds a spec.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Union

from agents.missions.spec import MissionError, MissionSpec, spec_convert

if TYPE_CHECKING:
    from agents.missions.kit import MissionRunner

#: Where the missions' folders are.
MISSIONS_DIR = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Sensor:
    """A sensor a mission needs and the agent opens when its configuration has the
    ``section`` (the search's ``thermal`` camera).

    ``check(options)`` validates the section without opening anything (ValueError
    naming the key). ``create(options, pose)`` returns the sensor, an async context
    manager the agent enters for its whole life; ``pose()`` is the vehicle's pose.
    ``video(sensor, options)``, if given, is a video source showing it (the agent's
    ``video`` section with ``"source": section``); ValueError/TypeError on a bad option.
    """

    section: str
    check: Callable[[Mapping[str, Any]], None]
    create: Callable[[Mapping[str, Any], Callable[[], Any]], Any]
    video: Callable[[Any, Mapping[str, Any]], Any] | None = None


@dataclass(frozen=True)
class Mission:
    """What a mission declares: its folder ``name``, a ``title`` for people, its
    ``spec`` (a :class:`MissionSpec` subclass with a ``tag``), ``runner()`` returning its
    :class:`~agents.missions.kit.MissionRunner` subclass (imported then, not before) and
    the ``sensor`` it needs, if any."""

    name: str
    title: str
    spec: type[MissionSpec]
    runner: Callable[[], type[MissionRunner[Any]]]
    sensor: Sensor | None = None

    @property
    def kind(self) -> str:
        """The ``kind`` its spec travels under."""
        return self.spec.mission_kind()


class UnknownMission(KeyError):
    """No mission has this name or kind; the message names the installed ones."""

    def __str__(self) -> str:
        return str(self.args[0])


def mission_names() -> list[str]:
    """The installed missions: the packages under ``agents/missions/``, sorted."""
    return sorted(
        info.name
        for info in pkgutil.iter_modules([str(MISSIONS_DIR)])
        if info.ispkg and not info.name.startswith("_")
    )


def mission(name: str) -> Mission:
    """The mission in folder ``name``. Raises UnknownMission naming the installed ones
    (only the folders :func:`mission_names` lists are ever imported)."""
    names = mission_names()
    if name not in names:
        raise UnknownMission(f"no mission {name!r}; installed: {', '.join(names) or 'none'}")
    module = importlib.import_module(f"{__package__}.{name}")
    declared = getattr(module, "MISSION", None)
    if not isinstance(declared, Mission) or declared.name != name:
        raise UnknownMission(f"agents/missions/{name}/ declares no MISSION named {name!r}")
    return declared


@functools.cache
def missions() -> dict[str, Mission]:
    """Every installed mission by ``kind``. Raises UnknownMission when two declare the
    same kind."""
    by_kind: dict[str, Mission] = {}
    for name in mission_names():
        declared = mission(name)
        if declared.kind in by_kind:
            other = by_kind[declared.kind].name
            raise UnknownMission(f"missions {other!r} and {name!r} both declare {declared.kind!r}")
        by_kind[declared.kind] = declared
    return by_kind


def mission_of(spec: MissionSpec) -> Mission:
    """The mission that flies ``spec``."""
    kind = type(spec).mission_kind()
    found = missions().get(kind)
    if found is None:
        raise UnknownMission(f"no mission flies {kind!r}")
    return found


@functools.cache
def mission_union() -> Any:
    """The tagged union of every installed mission's spec: what the vehicle task's
    ``mission`` claim decodes to (``Union[SearchSpec, ...]``)."""
    specs = tuple(m.spec for m in missions().values())
    if not specs:
        return MissionSpec
    return Union[specs]  # noqa: UP007 - built from a tuple, which `|` cannot take


def mission_decode(data: Any) -> MissionSpec:
    """The spec ``data`` (a JSON object with a ``kind``) describes. Raises MissionError
    naming the field: an unknown kind, a missing, unknown or ill-typed field, a value out
    of range, a rule across fields."""
    spec: MissionSpec = spec_convert(data, mission_union())
    return spec


def sensors() -> dict[str, Sensor]:
    """The sensors the installed missions need, by configuration section."""
    return {m.sensor.section: m.sensor for m in missions().values() if m.sensor is not None}


__all__ = [
    "Mission",
    "MissionError",
    "Sensor",
    "UnknownMission",
    "mission",
    "mission_decode",
    "mission_names",
    "mission_of",
    "mission_union",
    "missions",
    "sensors",
]
