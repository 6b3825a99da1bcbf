"""A session's recorded video as the SFU leaves it, for tests without a Janus: real WebM
files (VP8 encoded with PyAV), and real ``.mjr`` recordings (the RTP packets Janus would
have written, VP8 packetised by aiortc) for ``janus-pp-rec`` to convert.

Janus's ``.mjr`` (its record.c): ``MJR00002``, a 2-byte length and a JSON header
(``t`` the medium, ``c`` the codec, ``s`` when the file was created and ``u`` when the
first packet was written, in µs); then for each RTP packet ``MEET``, its time since the
first in ms (4 bytes), its length (2 bytes) and the packet.
"""

from __future__ import annotations

import fractions
import io
import json
import struct
from pathlib import Path

import av
import numpy as np
from aiortc.codecs.vpx import Vp8Encoder
from aiortc.rtp import RtpPacket

from services import sfu
from services.models import Session

#: When each stretch's first packet was written (Janus's ``.mjr`` header, µs).
STARTS_US = (1795856400000000, 1795856460500000)
#: Frames a second of the videos made here.
FPS = 10


def _picture(i: int, shade: int) -> av.VideoFrame:
    return av.VideoFrame.from_ndarray(
        np.full((48, 64, 3), (shade + 7 * i) % 256, np.uint8), format="rgb24"
    )


def webm(frames: int, shade: int) -> bytes:
    """A real WebM: ``frames`` VP8 frames of 64x48 at 10 fps, of one grey."""
    out = io.BytesIO()
    with av.open(out, "w", format="webm") as container:
        stream = container.add_stream("libvpx", rate=FPS)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        for i in range(frames):
            for packet in stream.encode(_picture(i, shade)):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return out.getvalue()


def decoded_frames(body: bytes) -> int:
    with av.open(io.BytesIO(body)) as container:
        return sum(1 for _ in container.decode(video=0))


def mjr_header(start_us: int) -> bytes:
    """A ``.mjr``'s header alone: a stretch whose first packet was written at
    ``start_us`` (Unix µs)."""
    header = json.dumps({"t": "v", "c": "vp8", "s": start_us - 1000, "u": start_us}).encode()
    return b"MJR00002" + struct.pack("!H", len(header)) + header


def mjr(frames: int, shade: int, start_us: int) -> bytes:
    """A real ``.mjr`` of ``frames`` VP8 frames of 64x48 at 10 fps (module docstring)."""
    encoder = Vp8Encoder()
    out = bytearray(mjr_header(start_us))
    seq = 1
    for i in range(frames):
        picture = _picture(i, shade)
        picture.pts, picture.time_base = i * 90000 // FPS, fractions.Fraction(1, 90000)
        payloads, timestamp = encoder.encode(picture, force_keyframe=i == 0)
        for n, payload in enumerate(payloads):
            packet = RtpPacket(
                payload_type=96,
                marker=int(n == len(payloads) - 1),  # the frame's last packet
                sequence_number=seq,
                timestamp=timestamp,
                ssrc=1234,
                payload=payload,
            ).serialize()
            seq += 1
            out += b"MEET" + struct.pack("!IH", i * 1000 // FPS, len(packet)) + packet
    return bytes(out)


def stretch_name(session: Session, start_us: int) -> str:
    """The name Janus gives a stretch of the session's video (without its suffix)."""
    return f"videoroom-{sfu.sfu_room(session.pk)}-user-1-{start_us - 1000}-video-0"


def recording_folder(session: Session) -> Path:
    """The session's recording folder (made if missing; an SFU must be configured)."""
    folder = sfu.sfu_recording_dir(session.pk)
    assert folder is not None
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def stretch_converted(session: Session, start_us: int, body: bytes) -> Path:
    """One stretch of the session's video as the SFU leaves it once converted: its
    ``.mjr`` (the header, saying it started at ``start_us``) and its ``.webm``
    (``body``). Returns the WebM's path."""
    folder = recording_folder(session)
    name = stretch_name(session, start_us)
    (folder / f"{name}.mjr").write_bytes(mjr_header(start_us))
    (folder / f"{name}.webm").write_bytes(body)
    return folder / f"{name}.webm"


def recorded(session: Session, videos: list[bytes]) -> Path:
    """The session's video as the SFU leaves it once converted: a stretch per video
    (:func:`stretch_converted`), started at :data:`STARTS_US`. Returns the folder."""
    for start_us, body in zip(STARTS_US, videos, strict=False):
        stretch_converted(session, start_us, body)
    return recording_folder(session)


def recorded_unconverted(session: Session, frames: list[int]) -> Path:
    """The session's video as Janus leaves it when the session ends: a real ``.mjr``
    per stretch (of ``frames[n]`` frames, started at :data:`STARTS_US`), not yet
    converted. Returns the folder."""
    folder = recording_folder(session)
    for n, (start_us, count) in enumerate(zip(STARTS_US, frames, strict=False)):
        (folder / f"{stretch_name(session, start_us)}.mjr").write_bytes(
            mjr(count, 40 + 80 * n, start_us)
        )
    return folder
