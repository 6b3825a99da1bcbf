"""Files a mission makes (its photos), kept on the vehicle until the platform has
them (docs/protocol.md, "Mission files").

One :class:`ArtifactStore` per agent. :meth:`ArtifactStore.put` writes the file and what
it is (``<directory>/<session>/<name>`` and ``<name>.json``) before anything is sent, so
an uplink outage or an agent restart loses nothing. It sends each file as ``artifact``
chunks under the protocol's frame limit through an :class:`agents.outbox.AckedOutbox` (a
few at a time, again on every new uplink and after RESEND_S without an answer), and
deletes the file once the platform has acknowledged every chunk. Photos never travel in
events or the flight record: a batch of telemetry is no place for 200 kB of JPEG, and the
session's log keeps only their digest.

The disk is bounded: a file that would take the waiting files over ``max_bytes`` is
refused (``put`` returns False and the caller goes on without it).
"""

from __future__ import annotations

import base64
import contextlib
import functools
import hashlib
import json
import logging
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Self

from agents.outbox import AckedOutbox, Build, UplinkPort
from agents.protocol.messages import (
    ARTIFACT_CHUNK_BYTES,
    ARTIFACT_MAX_BYTES,
    Ack,
    Artifact,
)

log = logging.getLogger(__name__)

#: Chunks sent and not yet acknowledged at a time, and how long before one is sent
#: again on the same uplink.
IN_FLIGHT: Final = 8
RESEND_S: Final = 10.0
#: How much may wait on the vehicle by default.
ARTIFACTS_MAX_BYTES: Final = 1024 * 1024 * 1024

_ID_PREFIX: Final = "artifact:"


def chunk_id(session_id: str, name: str, index: int) -> str:
    """The id of chunk ``index`` of a session's file ``name`` (what ``ack`` names)."""
    return f"{_ID_PREFIX}{session_id}:{name}:{index}"


@dataclass
class _File:
    session_id: str
    name: str
    path: Path
    media_type: str
    size: int
    sha256: str
    meta: dict[str, Any]
    acked: set[int] = field(default_factory=set)

    @property
    def count(self) -> int:
        return -(-self.size // ARTIFACT_CHUNK_BYTES)

    @property
    def key(self) -> tuple[str, str]:
        return (self.session_id, self.name)

    def chunk_ids(self) -> list[str]:
        return [chunk_id(self.session_id, self.name, index) for index in range(self.count)]


class ArtifactStore:
    """Keeps and uploads the files missions make (module docstring). Use as an async
    context manager: it uploads until the block ends. :attr:`uplink` is set once the
    uplink exists."""

    def __init__(self, *, directory: Path, max_bytes: int = ARTIFACTS_MAX_BYTES) -> None:
        self.directory = directory
        self.max_bytes = max_bytes
        #: Files waiting for the platform, oldest first.
        self.files: dict[tuple[str, str], _File] = {}
        #: Sends their chunks (one unit each, by :func:`chunk_id`).
        self.outbox = AckedOutbox(
            self._chunks,
            in_flight=IN_FLIGHT,
            resend_s=RESEND_S,
            name="artifact-upload",
            what="mission file upload",
        )

    @property
    def uplink(self) -> UplinkPort | None:
        """The uplink the chunks go through (the outbox's)."""
        return self.outbox.uplink

    @uplink.setter
    def uplink(self, uplink: UplinkPort | None) -> None:
        self.outbox.uplink = uplink

    async def __aenter__(self) -> Self:
        self.directory.mkdir(parents=True, exist_ok=True)
        self._load()
        self.outbox.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.outbox.stop()

    def _load(self) -> None:
        """Files a previous run left unacknowledged are sent again (all their chunks:
        acknowledgements are not kept, and the platform takes a chunk twice)."""
        for meta_path in sorted(self.directory.glob("*/*.json"), key=lambda p: p.stat().st_mtime):
            try:
                info = json.loads(meta_path.read_text())
                path = meta_path.with_suffix("")
                item = _File(
                    session_id=meta_path.parent.name,
                    name=path.name,
                    path=path,
                    media_type=str(info["media_type"]),
                    size=path.stat().st_size,
                    sha256=str(info["sha256"]),
                    meta=dict(info["meta"]),
                )
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.error("dropped unreadable mission file %s: %s", meta_path, exc)
                continue
            self.files[item.key] = item

    @property
    def waiting_bytes(self) -> int:
        return sum(item.size for item in self.files.values())

    def put(
        self, session_id: str, name: str, body: bytes, *, media_type: str, meta: Mapping[str, Any]
    ) -> bool:
        """Keep ``body`` as the file ``name`` of ``session_id`` with ``meta`` (a small
        JSON object) and send it. Returns False, keeping nothing, when it is empty or
        too big, the disk bound is reached, or it cannot be written; a file of the same
        name in the session replaces one not sent yet. Never raises."""
        if not body or len(body) > ARTIFACT_MAX_BYTES:
            log.error("mission file %s is %d bytes: not kept", name, len(body))
            return False
        if self.waiting_bytes + len(body) > self.max_bytes:
            log.error("mission file %s not kept: %d bytes wait already", name, self.waiting_bytes)
            return False
        folder = self.directory / session_id
        path = folder / name
        item = _File(
            session_id=session_id,
            name=name,
            path=path,
            media_type=media_type,
            size=len(body),
            sha256=hashlib.sha256(body).hexdigest(),
            meta=dict(meta),
        )
        try:
            folder.mkdir(parents=True, exist_ok=True)
            # The file first, then what it is: a file without its .json is not loaded.
            for target, data in (
                (path, body),
                (
                    path.with_name(f"{name}.json"),
                    json.dumps(
                        {"media_type": media_type, "sha256": item.sha256, "meta": meta}
                    ).encode(),
                ),
            ):
                tmp = target.with_name(f".{target.name}.tmp")
                tmp.write_bytes(data)
                os.replace(tmp, target)
        except (OSError, TypeError, ValueError) as exc:
            log.error("could not keep mission file %s: %s", path, exc)
            return False
        replaced = self.files.get(item.key)
        if replaced is not None:
            # Its chunks have the same ids: the new file's go now, not after RESEND_S.
            for unit_id in replaced.chunk_ids():
                self.outbox.forget(unit_id)
        self.files[item.key] = item
        self.outbox.wake()
        return True

    def pending(self, session_id: str) -> list[str]:
        """The names of ``session_id``'s files the platform does not have yet."""
        return [item.name for item in self.files.values() if item.session_id == session_id]

    def acked(self, ack: Ack) -> bool:
        """The platform's ``ack`` of a chunk; False if ``ack`` is not about one. A file
        whose every chunk is acknowledged goes; a refused chunk (not this vehicle's
        session, say) drops its whole file, logged: it would be refused again."""
        if not ack.id.startswith(_ID_PREFIX):
            return False
        rest = ack.id[len(_ID_PREFIX) :]
        session_id, _, tail = rest.partition(":")
        name, _, index = tail.rpartition(":")
        item = self.files.get((session_id, name))
        if item is None or not index.isdigit():
            return True
        if not ack.ok:
            log.error("the platform refused mission file %s: %s", ack.id, ack.detail)
            self._drop(item)
        else:
            item.acked.add(int(index))
            if len(item.acked) >= item.count:
                self._drop(item)
        self.outbox.acked(ack.id)
        return True

    def _drop(self, item: _File) -> None:
        self.files.pop(item.key, None)
        for unit_id in item.chunk_ids():
            self.outbox.forget(unit_id)
        for path in (item.path, item.path.with_name(f"{item.name}.json")):
            with contextlib.suppress(OSError):
                path.unlink()

    def _chunks(self) -> Iterator[tuple[str, Build]]:
        """The chunks not acknowledged yet, oldest file first (the outbox's units)."""
        for item in list(self.files.values()):
            yield from self._file_chunks(item)

    def _file_chunks(self, item: _File) -> Iterator[tuple[str, Build]]:
        # The body is read once a pass, for the first of its chunks the outbox sends.
        body: bytes | None = None

        def build(index: int) -> Artifact | None:
            nonlocal body
            if body is None:
                try:
                    body = item.path.read_bytes()
                except OSError as exc:
                    log.error("dropped unreadable mission file %s: %s", item.path, exc)
                    self._drop(item)
                    return None
            start = index * ARTIFACT_CHUNK_BYTES
            return Artifact(
                id=chunk_id(item.session_id, item.name, index),
                session_id=item.session_id,
                name=item.name,
                media_type=item.media_type,
                size=item.size,
                sha256=item.sha256,
                index=index,
                count=item.count,
                meta=item.meta,
                b64=base64.b64encode(body[start : start + ARTIFACT_CHUNK_BYTES]).decode(),
            )

        for index in range(item.count):
            if self.files.get(item.key) is not item:
                return  # dropped as unreadable: none of its chunks can go
            if index not in item.acked:
                yield chunk_id(item.session_id, item.name, index), functools.partial(build, index)
