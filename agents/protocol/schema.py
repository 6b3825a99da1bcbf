"""The published JSON Schema (draft 2020-12) of each WebSocket channel, generated from
the message structs of :mod:`agents.protocol.messages`, and of the vehicle task's
``mission`` claim, generated from the installed missions' specs.

    python -m agents.protocol.schema --write   # regenerate docs/protocol/schema/ and
                                               # agents/missions/*/spec.schema.json
    python -m agents.protocol.schema --check   # exit 1 when the files differ from the code

One self-contained file per channel, ``docs/protocol/schema/<channel>.schema.json``: the
channel's tagged union (``anyOf`` of ``$ref``, with an OpenAPI-style ``discriminator``
on ``type``) and every struct it uses under ``$defs``. Cross-field rules (repeated
command names, a default outside its min/max, min/max on a non-numeric argument) are
checked by ``parse_message`` only.

``docs/protocol/schema/mission.schema.json``: what every mission has (an object with a
``kind`` and an ``id``), without naming the missions; each mission's own spec is
published in its folder, ``agents/missions/<name>/spec.schema.json`` (generated from its
``spec.py``), and the ``kind`` says which of them applies. Adding a mission adds its
folder and nothing else. Their rules across fields (a start index past the last
waypoint, a drop above the cruise altitude) are the specs' own (``MissionSpec.check``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import msgspec

from agents.missions.registry import MISSIONS_DIR, missions
from agents.missions.spec import TAG_FIELD, MissionId
from agents.protocol.base import CHANNELS, PROTOCOL_VERSION
from agents.protocol.messages import CHANNEL_TYPES, ArgSpec

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "docs" / "protocol" / "schema"
_DIALECT = "https://json-schema.org/draft/2020-12/schema"


def channel_schema(channel: str) -> dict[str, Any]:
    """The JSON Schema of every message accepted on ``channel``. Raises KeyError for an
    unknown channel."""
    # ArgSpec is referenced from CommandSpec.args by hand (see messages.py), so it is
    # listed here to land in $defs.
    (root, _), defs = msgspec.json.schema_components(
        [CHANNEL_TYPES[channel], ArgSpec], ref_template="#/$defs/{name}"
    )
    if "CommandSpec" not in defs:
        del defs["ArgSpec"]
    return {
        "$schema": _DIALECT,
        "title": f"IoUV protocol v{PROTOCOL_VERSION}: {channel}",
        "description": "Generated from agents/protocol/messages.py; do not edit.",
        **root,
        "$defs": dict(sorted(defs.items())),
    }


def mission_schema() -> dict[str, Any]:
    """The JSON Schema of the vehicle task's ``mission`` claim: an object whose ``kind``
    names a mission and whose ``id`` names this one. The rest is the spec of the mission
    that declares the kind (:func:`mission_spec_schema`, published in its folder): the
    list of missions is the installation's, so this document does not repeat it."""
    id_schema = msgspec.json.schema(MissionId)
    return {
        "$schema": _DIALECT,
        "title": f"IoUV protocol v{PROTOCOL_VERSION}: vehicle task mission",
        "description": (
            "Generated from agents/missions/spec.py; do not edit. The mission's other "
            f"fields are those of the spec whose {TAG_FIELD!r} matches, published as "
            "agents/missions/<name>/spec.schema.json in the mission's folder."
        ),
        "type": "object",
        "properties": {TAG_FIELD: {"type": "string", "minLength": 1}, "id": id_schema},
        "required": [TAG_FIELD, "id"],
    }


def mission_spec_schema(name: str) -> dict[str, Any]:
    """The JSON Schema of the spec of the mission in folder ``name`` (its ``kind`` a
    constant). Raises KeyError for a folder that declares no mission."""
    declared = {m.name: m for m in missions().values()}[name]
    (root,), defs = msgspec.json.schema_components([declared.spec], ref_template="#/$defs/{name}")
    return {
        "$schema": _DIALECT,
        "title": f"IoUV protocol v{PROTOCOL_VERSION}: mission {declared.kind!r}",
        "description": f"Generated from agents/missions/{name}/spec.py; do not edit.",
        **root,
        "$defs": dict(sorted(defs.items())),
    }


def mission_spec_path(name: str, directory: Path = MISSIONS_DIR) -> Path:
    """Where the spec schema of the mission in folder ``name`` is published."""
    return directory / name / "spec.schema.json"


#: The published files besides the channels': name -> schema.
DOCUMENTS: dict[str, Any] = {"mission": mission_schema}


def _text(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def schema_text(channel: str) -> str:
    """The file content for ``channel`` (or a name of :data:`DOCUMENTS`): stable,
    indented JSON with a final newline."""
    return _text(DOCUMENTS[channel]() if channel in DOCUMENTS else channel_schema(channel))


def schema_path(channel: str, directory: Path = SCHEMA_DIR) -> Path:
    return directory / f"{channel}.schema.json"


def _published(directory: Path, missions_dir: Path) -> dict[Path, str]:
    """Every published file and its content: the channels', the mission document, and
    each mission's spec in its folder."""
    files = {schema_path(c, directory): schema_text(c) for c in (*CHANNELS, *DOCUMENTS)}
    for m in missions().values():
        files[mission_spec_path(m.name, missions_dir)] = _text(mission_spec_schema(m.name))
    return files


def stale_files(directory: Path = SCHEMA_DIR, missions_dir: Path = MISSIONS_DIR) -> list[Path]:
    """The schema files that are missing or differ from the code."""
    return [
        path
        for path, text in _published(directory, missions_dir).items()
        if not path.exists() or path.read_text(encoding="utf-8") != text
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", action="store_true", help="regenerate the files")
    action.add_argument("--check", action="store_true", help="exit 1 if a file is stale")
    parser.add_argument("--dir", type=Path, default=SCHEMA_DIR)
    parser.add_argument(
        "--missions-dir", type=Path, default=MISSIONS_DIR, help="where each mission's folder is"
    )
    args = parser.parse_args(argv)
    if args.write:
        for path, text in _published(args.dir, args.missions_dir).items():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            print(path)
        return 0
    stale = stale_files(args.dir, args.missions_dir)
    for path in stale:
        print(f"stale: {path} (run python -m agents.protocol.schema --write)", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
