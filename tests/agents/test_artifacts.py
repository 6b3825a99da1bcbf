"""The files missions make (agents.artifacts) wait on disk until the platform has every
chunk: sent a few at a time under the frame limit, again on a new uplink, deleted once
all are acknowledged, dropped whole when refused, and found again after a restart."""

from __future__ import annotations

import asyncio
import base64
import hashlib
import os
from pathlib import Path

from agents.artifacts import IN_FLIGHT, ArtifactStore
from agents.protocol import encode_message
from agents.protocol.base import MAX_MESSAGE_BYTES
from agents.protocol.messages import ARTIFACT_CHUNK_BYTES, Ack, Artifact, Message
from tests.agents.waiting import until as wait_until

BODY = os.urandom(10 * ARTIFACT_CHUNK_BYTES + 5)  # 11 chunks


class Port:
    """An uplink as the store sees it: connected or not, and what it was sent."""

    def __init__(self) -> None:
        self.connected = asyncio.Event()
        self.connections = 0
        self.sent: list[Artifact] = []

    def connect(self) -> None:
        self.connections += 1
        self.connected.set()

    def send(self, message: Message) -> None:
        assert isinstance(message, Artifact)
        assert len(encode_message(message, channel="uplink_to_platform")) < MAX_MESSAGE_BYTES
        self.sent.append(message)


def ack(message: Artifact, ok: bool = True) -> Ack:
    return Ack(id=message.id, ok=ok, detail="" if ok else "not a session of this vehicle")


async def test_a_photo_is_sent_in_chunks_and_deleted_once_all_are_acknowledged(
    tmp_path: Path,
) -> None:
    port = Port()
    async with ArtifactStore(directory=tmp_path) as store:
        store.uplink = port
        assert store.put("s-1", "photo-0001.jpg", BODY, media_type="image/jpeg", meta={"lat": 1})
        assert (tmp_path / "s-1" / "photo-0001.jpg").read_bytes() == BODY  # on disk first
        store.outbox.upload()
        assert port.sent == []  # no uplink yet
        port.connect()
        await wait_until(lambda: len(port.sent) == IN_FLIGHT, within=5)
        store.outbox.upload()
        assert len(port.sent) == IN_FLIGHT  # no more until some are acknowledged
        for message in list(port.sent):
            assert store.acked(ack(message))
        await wait_until(lambda: len(port.sent) == 11, within=5)
        for message in port.sent[IN_FLIGHT:]:
            store.acked(ack(message))
        assert store.pending("s-1") == []
        assert not (tmp_path / "s-1" / "photo-0001.jpg").exists()
    chunks = sorted(port.sent, key=lambda m: m.index)
    body = b"".join(base64.b64decode(m.b64) for m in chunks)
    assert body == BODY and chunks[0].sha256 == hashlib.sha256(BODY).hexdigest()
    assert [m.index for m in chunks] == list(range(11)) and chunks[0].meta == {"lat": 1}


async def test_unacknowledged_chunks_go_again_after_a_restart_and_a_refusal_drops_the_file(
    tmp_path: Path,
) -> None:
    port = Port()
    async with ArtifactStore(directory=tmp_path) as store:
        store.put("s-1", "a.jpg", BODY[:100], media_type="image/jpeg", meta={})
        store.put("s-2", "b.jpg", BODY[:200], media_type="image/jpeg", meta={})
        store.uplink = port
        port.connect()
        await wait_until(lambda: len(port.sent) == 2, within=5)
    # The agent restarts: both files are still there and go again on the new uplink.
    again = Port()
    async with ArtifactStore(directory=tmp_path) as store:
        assert sorted(store.files) == [("s-1", "a.jpg"), ("s-2", "b.jpg")]
        store.uplink = again
        again.connect()
        await wait_until(lambda: len(again.sent) == 2, within=5)
        first, second = sorted(again.sent, key=lambda m: m.session_id)
        store.acked(ack(first, ok=False))  # refused for good: dropped, not sent again
        store.acked(ack(second))
        assert store.files == {}
    assert not any(path.is_file() for path in tmp_path.rglob("*"))  # noqa: ASYNC240


async def test_a_file_over_the_bound_is_refused_and_nothing_is_kept(tmp_path: Path) -> None:
    async with ArtifactStore(directory=tmp_path, max_bytes=len(BODY) + 10) as store:
        assert store.put("s", "one.jpg", BODY, media_type="image/jpeg", meta={})
        assert not store.put("s", "two.jpg", BODY, media_type="image/jpeg", meta={})
        assert not store.put("s", "empty.jpg", b"", media_type="image/jpeg", meta={})
        assert store.pending("s") == ["one.jpg"]
