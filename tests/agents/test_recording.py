"""The agent's flight recorder alone: numbering, batches on disk until acknowledged, the
bound on what waits, the tlog framing (agents.recording)."""

from __future__ import annotations

import asyncio
import base64
import struct
from pathlib import Path
from typing import Any

import msgspec
import pytest

from agents.protocol import encode_message, parse_message
from agents.protocol.messages import Ack, Message, Record
from agents.recording import FlightRecorder, batch_id
from agents.vehicles.base import VehicleState


class FakeUplink:
    """What the recorder sends, parsed back as the platform would."""

    def __init__(self) -> None:
        self.connected = asyncio.Event()
        self.connections = 0
        self.sent: list[Record] = []

    def send(self, message: Message) -> None:
        parsed = parse_message(encode_message(message), channel="uplink_to_platform")
        assert isinstance(parsed, Record)
        self.sent.append(parsed)


def recorder(directory: Path, **kwargs: Any) -> FlightRecorder:
    state = VehicleState(lat=40.0, lon=-8.0, alt=5.0, speed_mps=2.0, armed=True, mode="GUIDED")
    return FlightRecorder(directory=directory, state=lambda: state, telemetry=dict, **kwargs)


def samples_on_disk(directory: Path) -> list[dict[str, Any]]:
    out: list[dict[str, Any]] = []
    for path in sorted(directory.glob("*/batch-*.json")):
        out.extend(msgspec.json.decode(path.read_bytes())["samples"])
    return out


async def test_a_session_is_numbered_without_gaps_and_kept_until_acknowledged(
    tmp_path: Path,
) -> None:
    uplink = FakeUplink()
    async with recorder(tmp_path) as rec:
        rec.uplink = uplink
        rec.session_start("s-1")
        rec.command(source="user", name="take_off", args={"altitude_m": 5}, ok=True, seq=1)
        rec.event("envelope_breach", "s-1", {"limit": "altitude"})
        rec.event("other", "s-2", {})  # another session's: not this record
        rec.raw(1_700_000_000.25, b"\xfd\x01\x02")
        await asyncio.sleep(1.3)  # telemetry sampled at 5 Hz while armed
        rec.session_end()
        seqs = [s["seq"] for s in samples_on_disk(tmp_path)]
        assert seqs == list(range(1, len(seqs) + 1))
        kinds = [s["kind"] for s in samples_on_disk(tmp_path)]
        assert kinds.count("telemetry") >= 5
        assert kinds.count("command") == 1 and kinds.count("event") == 1
        [tlog] = [s for s in samples_on_disk(tmp_path) if s["kind"] == "tlog"]
        raw = base64.b64decode(tlog["data"]["b64"])
        assert struct.unpack(">Q", raw[:8])[0] == 1_700_000_000_250_000
        assert raw[8:] == b"\xfd\x01\x02"

        # Nothing goes while the uplink is down; everything once it is up.
        await asyncio.sleep(1.2)
        assert uplink.sent == []
        uplink.connections = 1
        uplink.connected.set()
        rec.outbox.wake()
        await asyncio.sleep(0.2)
        sent = {m.id for m in uplink.sent}
        assert sent == set(rec.pending)
        for message in list(uplink.sent):
            assert rec.acked(Ack(id=message.id, ok=True))
        assert rec.pending == {}
        assert samples_on_disk(tmp_path) == []
        assert not rec.acked(Ack(id="m-1", ok=True))  # not a batch's


async def test_after_a_restart_the_numbering_goes_on_and_old_batches_are_sent(
    tmp_path: Path,
) -> None:
    async with recorder(tmp_path) as rec:
        rec.session_start("s-1")
        rec.command(source="mission", name="go_to_waypoint", args={}, ok=True)
        rec.flush()
    left = samples_on_disk(tmp_path)
    async with recorder(tmp_path) as again:
        assert set(again.pending) == {batch_id("s-1", 1)}
        again.session_start("s-1")
        again.flush()
        first_new = [s["seq"] for s in samples_on_disk(tmp_path)][len(left)]
        assert first_new == left[-1]["seq"] + 1


async def test_a_full_buffer_drops_telemetry_and_says_so_in_the_record(tmp_path: Path) -> None:
    async with recorder(tmp_path, max_bytes=1) as rec:
        rec.session_start("s-1")  # its first sample fits: nothing waits yet
        rec.flush()
        assert rec.pending_bytes > 1
        rec._sample_telemetry(1.0e9)
        rec.raw(1.0e9, b"x" * 10)
        rec.command(source="failsafe", name="land", args={}, ok=True)  # kept: under 2x
        # Room again: the next sample is preceded by what was dropped.
        for mid in list(rec.pending):
            rec.acked(Ack(id=mid, ok=True))
        rec._sample_telemetry(1.0e9 + 1)
        rec.flush()
    samples = samples_on_disk(tmp_path)  # after the first batch, acknowledged
    assert [s["seq"] for s in samples] == list(range(2, len(samples) + 2))
    [dropped] = [s for s in samples if s["kind"] == "dropped"]
    assert dropped["data"]["telemetry"] == 1 and dropped["data"]["tlog_bytes"] == 10


@pytest.mark.parametrize(
    "samples",
    [
        [
            {"seq": 1, "t": 1.0, "kind": "telemetry", "data": {}},
            {"seq": 3, "t": 1.0, "kind": "telemetry", "data": {}},
        ],
        [{"seq": 2, "t": 1.0, "kind": "telemetry", "data": {}}],
        [{"seq": 1, "t": 1.0, "kind": "video", "data": {}}],
    ],
)
def test_a_batch_with_a_gap_or_an_unknown_kind_is_refused(samples: list[dict[str, Any]]) -> None:
    frame = msgspec.json.encode(
        {"type": "record", "id": "record:s:1", "session_id": "s", "first": 1, "samples": samples}
    )
    with pytest.raises(Exception) as refused:
        parse_message(frame, channel="uplink_to_platform")
    assert getattr(refused.value, "code", "") == "bad_field"
