"""The published JSON Schema (draft 2020-12) of each WebSocket channel, generated from
the message structs of :mod:`agents.protocol.messages`.

    python -m agents.protocol.schema --write   # regenerate docs/protocol/schema/
    python -m agents.protocol.schema --check   # exit 1 when the files differ from the code

One self-contained file per channel, ``docs/protocol/schema/<channel>.schema.json``: the
channel's tagged union (``anyOf`` of ``$ref``, with an OpenAPI-style ``discriminator``
on ``type``) and every struct it uses under ``$defs``. Cross-field rules (repeated
command names, a default outside its min/max, min/max on a non-numeric argument) are
checked by ``parse_message`` only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import msgspec

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


def schema_text(channel: str) -> str:
    """The file content for ``channel``: stable, indented JSON with a final newline."""
    return json.dumps(channel_schema(channel), indent=2, ensure_ascii=False) + "\n"


def schema_path(channel: str, directory: Path = SCHEMA_DIR) -> Path:
    return directory / f"{channel}.schema.json"


def stale_files(directory: Path = SCHEMA_DIR) -> list[Path]:
    """The schema files that are missing or differ from the code."""
    return [
        path
        for channel in CHANNELS
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
        for channel in CHANNELS:
            schema_path(channel, args.dir).write_text(schema_text(channel), encoding="utf-8")
            print(schema_path(channel, args.dir))
        return 0
    stale = stale_files(args.dir)
    for path in stale:
        print(f"stale: {path} (run python -m agents.protocol.schema --write)", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
