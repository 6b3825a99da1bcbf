"""The published JSON Schema (draft 2020-12) of each WebSocket channel, generated from
the message structs of :mod:`agents.protocol.messages`, and of the vehicle task's
``mission`` claim, generated from the installed missions' specs.

    python -m agents.protocol.schema --write   # regenerate docs/protocol/schema/
    python -m agents.protocol.schema --check   # exit 1 when the files differ from the code

One self-contained file per channel, ``docs/protocol/schema/<channel>.schema.json``: the
channel's tagged union (``anyOf`` of ``$ref``, with an OpenAPI-style ``discriminator``
on ``type``) and every struct it uses under ``$defs``. Cross-field rules (repeated
command names, a default outside its min/max, min/max on a non-numeric argument) are
checked by ``parse_message`` only.

``docs/protocol/schema/mission.schema.json``: the tagged union of the missions' specs
(agents/missions/<name>/spec.py; ``discriminator`` on ``kind``). Its rules across fields
(a start index past the last waypoint, a drop above the cruise altitude) are the
specs' own (``MissionSpec.check``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import msgspec

from agents.missions.registry import mission_union
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
    """The JSON Schema of the vehicle task's ``mission`` claim: one of the installed
    missions' specs, by ``kind``."""
    (root,), defs = msgspec.json.schema_components([mission_union()], ref_template="#/$defs/{name}")
    return {
        "$schema": _DIALECT,
        "title": f"IoUV protocol v{PROTOCOL_VERSION}: vehicle task mission",
        "description": "Generated from agents/missions/*/spec.py; do not edit.",
        **root,
        "$defs": dict(sorted(defs.items())),
    }


#: The published files besides the channels': name -> schema.
DOCUMENTS: dict[str, Any] = {"mission": mission_schema}


def schema_text(channel: str) -> str:
    """The file content for ``channel`` (or a name of :data:`DOCUMENTS`): stable,
    indented JSON with a final newline."""
    schema = DOCUMENTS[channel]() if channel in DOCUMENTS else channel_schema(channel)
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def schema_path(channel: str, directory: Path = SCHEMA_DIR) -> Path:
    return directory / f"{channel}.schema.json"


def stale_files(directory: Path = SCHEMA_DIR) -> list[Path]:
    """The schema files that are missing or differ from the code."""
    return [
        path
        for channel in (*CHANNELS, *DOCUMENTS)
        if not (path := schema_path(channel, directory)).exists()
        or path.read_text(encoding="utf-8") != schema_text(channel)
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", action="store_true", help="regenerate the files")
    action.add_argument("--check", action="store_true", help="exit 1 if a file is stale")
    parser.add_argument("--dir", type=Path, default=SCHEMA_DIR)
    args = parser.parse_args(argv)
    if args.write:
        args.dir.mkdir(parents=True, exist_ok=True)
        for channel in (*CHANNELS, *DOCUMENTS):
            schema_path(channel, args.dir).write_text(schema_text(channel), encoding="utf-8")
            print(schema_path(channel, args.dir))
        return 0
    stale = stale_files(args.dir)
    for path in stale:
        print(f"stale: {path} (run python -m agents.protocol.schema --write)", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
