"""Parse + validate and encode time per protocol message, one realistic message per type.

    python -m benchmarks.protocol_codec [--repeats 7] [--number 2000] [--type heartbeat]

For each message it times :func:`agents.protocol.parse_message` (UTF-8 text in: decode,
validate, build the result) and :func:`agents.protocol.encode_message` (the parsed result
back to wire text, without re-validation), in microseconds per message: the median of
``--repeats`` runs of ``--number`` calls each. Messages are built as the agent and the
platform send them (a heartbeat with car telemetry, a profile with the car's commands,
a relay carrying a command...). Nothing is asserted; the table is for comparing codecs.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import timeit
from typing import Any

from agents.protocol import PROTOCOL_VERSION, encode_message, parse_message

_POSITION = {"lat": 48.1374, "lon": 11.5755, "alt": 519.5}

_COMMANDS: list[dict[str, Any]] = [
    {
        "name": "drive",
        "description": "Throttle and steering, each -1..1",
        "group": "motion",
        "args": {
            "throttle": {"type": "number", "min": -1, "max": 1, "default": 0},
            "steering": {"type": "number", "min": -1, "max": 1, "default": 0},
        },
    },
    {"name": "stop", "args": {}, "description": "Stop now", "group": "motion"},
    {
        "name": "set_speed_limit",
        "args": {"mps": {"type": "number", "min": 0.1, "max": 5, "unit": "m/s"}},
    },
    {"name": "horn", "args": {"duration_ms": {"type": "integer", "min": 50, "max": 2000}}},
    {"name": "lights", "args": {"on": {"type": "boolean"}}},
    {"name": "say", "args": {"text": {"type": "string", "default": "hello"}}},
]

_TELEMETRY = {
    "speed_mps": 1.25,
    "heading_deg": 87.5,
    "battery_v": 7.42,
    "motor_temp_c": 41.2,
    "throttle": 0.4,
    "steering": -0.1,
    "obstacle_cm": 132,
    "armed": True,
}

#: (label, channel, message) for every benchmarked message.
MESSAGES: list[tuple[str, str, dict[str, Any]]] = [
    (
        "hello",
        "uplink_to_platform",
        {"type": "hello", "v": PROTOCOL_VERSION, "vehicle_id": "car-7", "credential": "c" * 43},
    ),
    (
        "profile",
        "uplink_to_platform",
        {
            "type": "profile",
            "vehicle_type": "car",
            "adapter": "car_gpio",
            "attributes": {"max_speed_mps": 2.0, "wheelbase_m": 0.26, "camera": True},
            "commands": _COMMANDS,
            "telemetry": list(_TELEMETRY),
            "control_url": "wss://car-7.example.org:8765/control",
            "video": True,
            "position": _POSITION,
            "battery": 87.5,
            "safe_actions": {"stop": "The car brakes and stays where it is."},
            "session_id": None,
            "controller": False,
            "status": "idle",
        },
    ),
    (
        "heartbeat",
        "uplink_to_platform",
        {
            "type": "heartbeat",
            "seq": 1234,
            "position": _POSITION,
            "battery": 86.0,
            "status": "busy",
            "telemetry": _TELEMETRY,
        },
    ),
    (
        "event",
        "uplink_to_platform",
        {"type": "event", "session_id": "s-42", "event": "arrived", "data": {"waypoint": 3}},
    ),
    (
        "relay (to client)",
        "uplink_to_platform",
        {
            "type": "relay",
            "session_id": "s-42",
            "conn": "c1",
            "payload": {"type": "telemetry", "t": 1764000000.25, "data": _TELEMETRY},
        },
    ),
    (
        "welcome (uplink)",
        "uplink_to_agent",
        {"type": "welcome", "v": PROTOCOL_VERSION, "heartbeat_interval_s": 5},
    ),
    ("task", "uplink_to_agent", {"type": "task", "token": "t" * 600, "id": "17"}),
    (
        "relay (to agent)",
        "uplink_to_agent",
        {
            "type": "relay",
            "session_id": "s-42",
            "conn": "c1",
            "payload": {
                "type": "command",
                "seq": 12,
                "name": "drive",
                "args": {"throttle": 0.5, "steering": 0},
            },
        },
    ),
    (
        "command",
        "control_to_agent",
        {"type": "command", "seq": 12, "name": "drive", "args": {"throttle": 0.5, "steering": 0}},
    ),
    (
        "subscribe",
        "control_to_agent",
        {"type": "subscribe", "topics": ["speed_mps", "heading_deg"], "rate_hz": 10},
    ),
    ("ping", "control_to_agent", {"type": "ping", "t": 1764000000.25}),
    (
        "welcome (control)",
        "control_to_client",
        {
            "type": "welcome",
            "role": "controller",
            "vehicle": {"id": "car-7", "type": "car"},
            "commands": _COMMANDS,
            "telemetry": list(_TELEMETRY),
        },
    ),
    ("ack", "control_to_client", {"type": "ack", "seq": 12, "ok": True, "error": None}),
    (
        "telemetry",
        "control_to_client",
        {"type": "telemetry", "t": 1764000000.25, "data": _TELEMETRY},
    ),
]


def _per_call_us(func: Any, number: int, repeats: int) -> float:
    runs = timeit.repeat(func, number=number, repeat=repeats)
    return statistics.median(runs) / number * 1e6


def measure(number: int, repeats: int, only: str | None = None) -> list[dict[str, Any]]:
    """Return one row per message: label, channel, bytes, parse_us, encode_us."""
    rows = []
    for label, channel, message in MESSAGES:
        if only and not label.startswith(only):
            continue
        text = json.dumps(message, separators=(",", ":"))
        parsed = parse_message(text, channel=channel)  # type: ignore[arg-type]
        rows.append(
            {
                "label": label,
                "channel": channel,
                "bytes": len(text),
                "parse_us": _per_call_us(
                    lambda: parse_message(text, channel=channel),  # type: ignore[arg-type]  # noqa: B023
                    number,
                    repeats,
                ),
                "encode_us": _per_call_us(
                    lambda: encode_message(parsed),  # noqa: B023
                    number,
                    repeats,
                ),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--number", type=int, default=2000, help="calls per run")
    parser.add_argument("--repeats", type=int, default=7, help="runs; the median is shown")
    parser.add_argument("--type", default=None, help="only messages whose label starts so")
    args = parser.parse_args()
    rows = measure(args.number, args.repeats, args.type)
    print(
        f"machine: {platform.node()} {platform.processor() or platform.machine()}, "
        f"python {platform.python_version()}"
    )
    print(f"median of {args.repeats} runs x {args.number} calls, microseconds per message\n")
    print(f"{'message':20}{'channel':20}{'bytes':>7}{'parse':>9}{'encode':>9}")
    for row in rows:
        print(
            f"{row['label']:20}{row['channel']:20}{row['bytes']:7d}"
            f"{row['parse_us']:9.2f}{row['encode_us']:9.2f}"
        )
    total_parse = sum(r["parse_us"] for r in rows)
    total_encode = sum(r["encode_us"] for r in rows)
    print(f"{'sum':47}{total_parse:9.2f}{total_encode:9.2f}")


if __name__ == "__main__":
    main()
