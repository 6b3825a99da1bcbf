"""Video from the vehicle to browsers over WebRTC, with one encoder shared by all viewers.

The agent's control WebSocket carries the signalling (``docs/video.md``); this module
owns everything after it:

* :class:`VideoService` is the camera behind every WebRTC connection: the connections
  themselves are :mod:`agents.rtc`'s, one per user, negotiated in one flow (the
  browser offers, ``webrtc_offer`` -> ``webrtc_answer``), and each that asks for video
  gets the camera with :meth:`VideoService.attach`.
* The vehicle's frames are **encoded once** (VP8, libvpx through PyAV) by a shared
  encoder and the resulting ``av.Packet``\\ s are handed to every viewer's
  ``RTCRtpSender``. aiortc's sender packetises a packet without re-encoding it
  (``RTCRtpSender._next_encoded_frame`` calls ``Encoder.pack`` for anything that is not
  an ``av.Frame``, the path ``MediaPlayer(decode=False)`` uses), so the CPU cost of
  video does not grow with the number of viewers. A viewer's picture-loss requests
  (PLI/FIR) are routed to the shared encoder, which then emits a keyframe for everyone.
* The source is polled only while at least one viewer's sender is actually pulling
  frames (a connected peer): a connection not yet up or an idle vehicle captures
  nothing, and the source is closed (camera released) when the last viewer leaves.
* Sources (:class:`VideoSource`): :class:`SyntheticCamera` draws a scene from the
  vehicle's pose with a frame counter and a timestamp readable from the pixels
  (:func:`read_frame_code`); :class:`V4L2Camera` reads a Linux camera (Raspberry Pi
  camera, USB webcam); :class:`MjpegCamera` reads an HTTP MJPEG stream (ESP32-CAM).
  A mission's sensor may add its own source (the search mission's thermal camera in
  false colour, :mod:`agents.missions.search.video`), handed in as ``sources``.
  :func:`video_source_create` builds one from the agent's configuration.

Nothing here imports Django: this runs on the vehicle's companion computer.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import contextvars
import logging
import math
import time
import urllib.parse
import zlib
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from types import TracebackType
from typing import (
    Any,
    Final,
    NamedTuple,
    Protocol,
    Self,
    TypeAlias,
    TypeVar,
    runtime_checkable,
)

import av
import av.video.frame
import numpy as np
import numpy.typing as npt
from aiortc import (
    MediaStreamTrack,
    RTCIceServer,
    RTCPeerConnection,
    RTCRtpCodecCapability,
    RTCRtpSender,
)
from aiortc.mediastreams import MediaStreamError
from aiortc.rtp import (
    RTCP_PSFB_APP,
    RTCP_RTPFB_NACK,
    AnyRtcpPacket,
    RtcpPsfbPacket,
    RtcpRrPacket,
    RtcpRtpfbPacket,
    RtcpSrPacket,
    unpack_remb_fci,
)

from agents.geo import local_offset_m
from agents.video_rate import RateController, RetransmitBudget, Role, fit_size

__all__ = [
    "CODE_BITS",
    "SERVICE_OPTIONS",
    "CameraPose",
    "FrameCode",
    "MjpegCamera",
    "SharedVp8Encoder",
    "SyntheticCamera",
    "V4L2Camera",
    "VideoError",
    "VideoService",
    "VideoSource",
    "VideoStatus",
    "draw_text",
    "read_frame_code",
    "restrict_ice_host_addresses",
    "stamp_frame_code",
    "video_service_create",
    "video_source_create",
]

logger = logging.getLogger(__name__)

RGB: TypeAlias = npt.NDArray[np.uint8]
_Packet: TypeAlias = "av.Packet[Any]"
_T = TypeVar("_T")

#: RTP video clock (90 kHz); packet timestamps are expressed in it.
VIDEO_TIME_BASE: Final = Fraction(1, 90_000)
#: Bits per row of the machine-readable code stamped at the top of synthetic frames.
CODE_BITS: Final = 48


class VideoError(Exception):
    """A video request could not be served: bad SDP, unknown peer, no common codec, too
    many viewers, bad source configuration. ``str(exc)`` is a sentence for the client."""


# --------------------------------------------------------------------------------------
# ICE host candidates
# --------------------------------------------------------------------------------------

# aioice offers every address of every interface except 127.0.0.1, and has no per-
# connection option to choose them. We wrap its module-level get_host_addresses once so
# that it honours this context variable; unset (the default) it behaves exactly as
# before, so other aiortc users in the process are unaffected. aiortc gathers inside
# setLocalDescription, in tasks that inherit the caller's context, so setting the
# variable around that call scopes the restriction to one peer connection.
_ICE_HOST_ADDRESSES: contextvars.ContextVar[tuple[str, ...] | None] = contextvars.ContextVar(
    "iouv_ice_host_addresses", default=None
)


def _install_ice_host_hook() -> None:
    import aioice.ice

    original = aioice.ice.get_host_addresses
    if getattr(original, "_iouv_hook", False):
        return

    def get_host_addresses(use_ipv4: bool, use_ipv6: bool) -> list[str]:
        only = _ICE_HOST_ADDRESSES.get()
        if only is None:
            return original(use_ipv4, use_ipv6)
        return [a for a in only if (use_ipv6 if ":" in a else use_ipv4)]

    get_host_addresses._iouv_hook = True  # type: ignore[attr-defined]
    aioice.ice.get_host_addresses = get_host_addresses


@contextlib.contextmanager
def restrict_ice_host_addresses(addresses: Sequence[str] | None) -> Iterator[None]:
    """Within the block (and tasks started from it), aioice offers only ``addresses`` as
    host candidates; None leaves aioice's choice. For loopback-only setups
    (``["127.0.0.1"]``), which aioice otherwise never offers."""
    if addresses is None:
        yield
        return
    _install_ice_host_hook()
    token = _ICE_HOST_ADDRESSES.set(tuple(addresses))
    try:
        yield
    finally:
        _ICE_HOST_ADDRESSES.reset(token)


# --------------------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------------------


@runtime_checkable
class VideoSource(Protocol):
    """Where the vehicle's pictures come from.

    ``frame()`` returns the next picture, paced by the source (a camera's frame rate, a
    synthetic source's ``fps``); the caller never needs to sleep. Sources open their
    device lazily on the first ``frame()``. ``close()`` releases the device; it is
    idempotent and not final: :class:`VideoService` closes the source when the last
    viewer leaves and calls ``frame()`` again when the next one arrives.
    """

    async def frame(self) -> av.VideoFrame: ...

    async def close(self) -> None: ...


class FrameCode(NamedTuple):
    """What :func:`read_frame_code` recovers from a frame's top rows."""

    counter: int  # frames drawn by the source since it was created
    ts_ms: int  # Unix time, milliseconds, when the frame was drawn


def _code_layout(width: int) -> tuple[int, int]:
    """(block size, left margin) of the code rows for a frame ``width`` pixels wide."""
    block = width // CODE_BITS
    if block < 4:
        raise ValueError(f"frames must be at least {4 * CODE_BITS} pixels wide for the code")
    return block, (width - block * CODE_BITS) // 2


def _code_check(counter: int, ts_ms: int) -> int:
    return zlib.crc32(counter.to_bytes(4, "big") + ts_ms.to_bytes(6, "big")) & 0xFFFF


def stamp_frame_code(img: RGB, counter: int, ts_ms: int) -> None:
    """Draw ``counter`` and ``ts_ms`` as two rows of black/white blocks at the top of
    ``img`` (H x W x 3, uint8, modified in place).

    Row 0: 32-bit counter then a 16-bit check (CRC-32 of counter and timestamp); row 1:
    48-bit Unix milliseconds. Blocks are ``W // 48`` pixels square, MSB first, centred:
    big enough to survive lossy video coding, so a test or a browser can recover the
    exact numbers (and so the capture-to-display latency) from a decoded frame.
    """
    block, x0 = _code_layout(img.shape[1])
    counter &= 0xFFFF_FFFF
    ts_ms &= 0xFFFF_FFFF_FFFF
    rows = ((counter << 16) | _code_check(counter, ts_ms), ts_ms)
    for r, value in enumerate(rows):
        bits = (value >> np.arange(CODE_BITS - 1, -1, -1)) & 1
        # One row of per-block values, widened to pixels and stacked to block height.
        line = np.repeat(bits.astype(np.uint8) * 255, block)
        img[r * block : (r + 1) * block, x0 : x0 + block * CODE_BITS] = line[None, :, None]


def read_frame_code(img: RGB) -> FrameCode | None:
    """Recover the code :func:`stamp_frame_code` drew, or None when the check fails (not
    a synthetic frame, or too damaged). Samples the middle half of each block."""
    block, x0 = _code_layout(img.shape[1])
    lo, hi = block // 4, block - block // 4
    values = []
    for r in range(2):
        band = img[r * block + lo : r * block + hi, x0 : x0 + block * CODE_BITS].astype(np.int32)
        if band.shape[0] == 0:
            return None
        # mean over rows and channels, then per block over its middle columns
        cols = band.mean(axis=(0, 2)).reshape(CODE_BITS, block)[:, lo:hi].mean(axis=1)
        value = 0
        for bit in cols > 127:
            value = (value << 1) | int(bit)
        values.append(value)
    counter, check = values[0] >> 16, values[0] & 0xFFFF
    if _code_check(counter, values[1]) != check:
        return None
    return FrameCode(counter, values[1])


# Seven-segment font: segments a (top), b (top right), c (bottom right), d (bottom),
# e (bottom left), f (top left), g (middle).
_SEGMENTS: Final[dict[str, str]] = {
    "0": "abcdef",
    "1": "bc",
    "2": "abged",
    "3": "abgcd",
    "4": "fgbc",
    "5": "afgcd",
    "6": "afgedc",
    "7": "abc",
    "8": "abcdefg",
    "9": "abcdfg",
    "-": "g",
    " ": "",
}


def draw_text(img: RGB, text: str, x: int, y: int, height: int, color: tuple[int, ...]) -> int:
    """Draw ``text`` (digits, space, '-', ':', '.') in a seven-segment font with its top
    left corner at (x, y); returns the x after the last character. Characters that fall
    outside ``img`` are clipped by numpy slicing."""
    w, t = height // 2, max(2, height // 8)
    mid = height // 2 - t // 2
    rgb = np.asarray(color, dtype=np.uint8)
    for ch in text:
        if ch in ":.":
            dot_rows = (height // 3, 2 * height // 3) if ch == ":" else (height - t,)
            for dy in dot_rows:
                img[y + dy : y + dy + t, x : x + t] = rgb
            x += t * 3
            continue
        boxes = {
            "a": (0, t, 0, w),
            "d": (height - t, height, 0, w),
            "g": (mid, mid + t, 0, w),
            "f": (0, height // 2, 0, t),
            "e": (height // 2, height, 0, t),
            "b": (0, height // 2, w - t, w),
            "c": (height // 2, height, w - t, w),
        }
        for seg in _SEGMENTS.get(ch, ""):
            r0, r1, c0, c1 = boxes[seg]
            img[y + r0 : y + r1, x + c0 : x + c1] = rgb
        x += w + t * 2
    return x


@dataclass(frozen=True)
class CameraPose:
    """What :class:`SyntheticCamera` draws from. Angles in degrees, heading clockwise
    from north; ``pan_deg`` adds to heading, ``tilt_deg`` > 0 looks up. Obstacles are
    ``(lat, lon, radius_m, height_m)`` pillars."""

    lat: float = 0.0
    lon: float = 0.0
    alt: float = 0.0  # metres above home
    heading_deg: float = 0.0
    pan_deg: float = 0.0
    tilt_deg: float = 0.0
    obstacles: Sequence[tuple[float, float, float, float]] = field(default_factory=tuple)

    @classmethod
    def coerce(cls, value: CameraPose | Mapping[str, Any] | Sequence[Any] | Any) -> CameraPose:
        """Accept a CameraPose; a mapping with its field names (``heading``, ``pan``,
        ``tilt`` also work); a tuple ``(lat, lon, alt, heading[, extras mapping])``; or
        any object with the attributes (e.g. the adapter's ``VehicleState``). None
        counts as 0. Obstacles are ``(lat, lon, radius_m[, height_m=2])``."""
        if isinstance(value, CameraPose):
            return value
        if isinstance(value, tuple | list):
            lat, lon, alt, heading = [*value, None, None, None, None][:4]
            extras = value[4] if len(value) > 4 and isinstance(value[4], Mapping) else {}
            value = {"lat": lat, "lon": lon, "alt": alt, "heading_deg": heading, **extras}

        def get(name: str, *aliases: str) -> Any:
            for key in (name, *aliases):
                v = value.get(key) if isinstance(value, Mapping) else getattr(value, key, None)
                if v is not None:
                    return v
            return None

        obstacles = []
        for o in get("obstacles") or ():
            lat_o, lon_o, radius, *height = (float(x) for x in o)
            obstacles.append((lat_o, lon_o, radius, height[0] if height else 2.0))
        return cls(
            lat=float(get("lat") or 0.0),
            lon=float(get("lon") or 0.0),
            alt=float(get("alt") or 0.0),
            heading_deg=float(get("heading_deg", "heading") or 0.0),
            pan_deg=float(get("pan_deg", "pan") or 0.0),
            tilt_deg=float(get("tilt_deg", "tilt") or 0.0),
            obstacles=tuple(obstacles),
        )


_SKY_TOP = np.array([38, 88, 170], dtype=np.float32)
_SKY_HORIZON = np.array([178, 206, 232], dtype=np.float32)
_MOUNTAIN = np.array([96, 104, 128], dtype=np.uint8)


class _Scene(NamedTuple):
    """What the synthetic camera draws below the horizon (near, far, the grid's lines)
    and how high the far skyline rises (a fraction of the picture)."""

    near: npt.NDArray[np.float32]
    far: npt.NDArray[np.float32]
    grid: npt.NDArray[np.float32]
    skyline: float


#: The scenes a synthetic camera draws: grass and hills for a car or a drone over land;
#: water with wave lines and a low, far coast for a boat.
SCENES: Final[dict[str, _Scene]] = {
    "land": _Scene(
        near=np.array([72, 122, 52], dtype=np.float32),
        far=np.array([150, 170, 150], dtype=np.float32),
        grid=np.array([34, 60, 26], dtype=np.float32),
        skyline=0.06,
    ),
    "sea": _Scene(
        near=np.array([22, 74, 122], dtype=np.float32),
        far=np.array([120, 160, 196], dtype=np.float32),
        grid=np.array([70, 124, 170], dtype=np.float32),
        skyline=0.012,
    ),
}


class SyntheticCamera:
    """A camera that draws what a vehicle at ``pose()`` would roughly see.

    Sky with mountains and compass ticks that turn with the heading, a ground grid (2 m
    squares on the ground, coarser when flying high) that moves with the vehicle's
    position (``scene`` ``"sea"``: water with wave lines under a low, far coast, for a
    boat), obstacles as orange pillars, the heading at the top, and at the bottom the
    frame counter and the UTC time of day in large seven-segment digits. The top two
    block rows carry the counter and Unix milliseconds exactly (:func:`read_frame_code`).

    ``pose`` is called once per frame on the event loop and returns a
    :class:`CameraPose`, a mapping with its field names, or an object with those
    attributes (the adapter's ``VehicleState``). The first position seen is the origin
    of the grid. Drawing runs in a worker thread (a few ms at 640x480) so it does not
    hold up the agent's control loop.
    """

    def __init__(
        self,
        width: int = 640,
        height: int = 480,
        fps: float = 15.0,
        pose: Callable[[], CameraPose | Mapping[str, Any] | Any] | None = None,
        *,
        hfov_deg: float = 70.0,
        mount_height_m: float = 0.5,
        scene: str = "land",
    ) -> None:
        if scene not in SCENES:
            raise ValueError(f"scene must be one of {', '.join(sorted(SCENES))}")
        self._scene = SCENES[scene]
        if width % 2 or height % 2 or height < 64:
            raise ValueError("width and height must be even and the height at least 64")
        _code_layout(width)  # raises when too narrow for the code rows
        if not 0 < fps <= 60:
            raise ValueError("fps must be in (0, 60]")
        self.width, self.height, self.fps = width, height, fps
        self._pose = pose or CameraPose
        self._focal = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
        self._mount = mount_height_m
        self._origin: tuple[float, float] | None = None
        self._next_t: float | None = None
        self._sky_cache: tuple[int, RGB] | None = None
        #: frames drawn so far; the number stamped into the next frame
        self.counter = 0
        u = (np.arange(width, dtype=np.float32) - width / 2 + 0.5) / self._focal
        self._u = u  # tangent of each column's angle from the optical axis
        self._col_az = np.degrees(np.arctan(u))  # each column's azimuth offset
        self._tick_tol = math.degrees(0.6 / self._focal)  # ~one column at the centre

    async def frame(self) -> av.VideoFrame:
        """The next frame, ``1/fps`` after the previous one (no catch-up burst after a
        stall: a late consumer gets the current scene, not a backlog)."""
        period = 1.0 / self.fps
        now = time.monotonic()
        if self._next_t is None or self._next_t < now - period:
            self._next_t = now
        await asyncio.sleep(max(0.0, self._next_t - now))
        self._next_t += period
        pose = CameraPose.coerce(self._pose())
        counter, ts_ms = self.counter, int(time.time() * 1000)
        self.counter += 1
        img = await asyncio.to_thread(self.render, pose, counter, ts_ms)
        return av.VideoFrame.from_ndarray(img, format="rgb24")

    async def close(self) -> None:
        """Nothing to release; restarts pacing on the next frame."""
        self._next_t = None

    def render(self, pose: CameraPose, counter: int, ts_ms: int) -> RGB:
        """Draw one frame (H x W x 3 RGB). Pure numpy; public for tests and benchmarks."""
        w, h, f = self.width, self.height, self._focal
        img = np.empty((h, w, 3), dtype=np.uint8)
        heading = (pose.heading_deg + pose.pan_deg) % 360.0
        cy = h / 2
        tilt = math.radians(max(-60.0, min(60.0, pose.tilt_deg)))
        horizon = round(cy + f * math.tan(tilt))  # looking up lowers the horizon
        hz = min(max(horizon, 0), h)

        # Sky: vertical gradient, deeper blue away from the horizon.
        if hz > 0:
            img[:hz] = self._sky(horizon)[:hz]
            # Mountains: a periodic silhouette of azimuth, so turning slides it sideways.
            az = np.radians(heading + self._col_az)
            rise = self._scene.skyline
            mh = (
                h * rise * (1.3 + np.sin(3 * az) + 0.5 * np.sin(7 * az + 1.0))
                + h * rise / 3 * np.sin(17 * az)
            ).astype(np.int32)
            band_h = min(int(h * 0.2), hz)
            if band_h > 0:
                rows = np.arange(hz - band_h, hz)[:, None]
                mask = rows >= (horizon - mh)[None, :]
                np.copyto(img[hz - band_h : hz], _MOUNTAIN, where=mask[:, :, None])
            # Compass ticks every 10 degrees, tall ones at the cardinal points.
            az_deg = (heading + self._col_az) % 360.0
            near = np.abs(((az_deg + 5.0) % 10.0) - 5.0) < self._tick_tol
            for col in np.nonzero(near)[0]:
                cardinal = abs(((az_deg[col] + 45.0) % 90.0) - 45.0) < 5.0
                tick = h // 12 if cardinal else h // 40
                img[max(0, hz - tick) : hz, col] = (255, 255, 255) if cardinal else (40, 40, 60)

        # Ground: each pixel below the horizon hit at distance d; lines where the world
        # coordinates cross multiples of the grid spacing, fogged with distance.
        if hz < h:
            cam_h = max(pose.alt, 0.0) + self._mount
            spacing = 2.0 if cam_h < 15 else (10.0 if cam_h < 150 else 50.0)
            if self._origin is None:
                self._origin = (pose.lat, pose.lon)
            north0, east0 = local_offset_m(self._origin, (pose.lat, pose.lon))
            dy = np.arange(hz, h, dtype=np.float32) - horizon + 0.5
            d = cam_h * f / np.maximum(dy, 0.5)  # distance of each row's ground point
            psi = math.radians(heading)
            c, s = math.cos(psi), math.sin(psi)
            u = self._u[None, :]
            a = (d / spacing)[:, None]
            gn = a * (c - u * s) + north0 / spacing  # world position in grid units
            ge = a * (s + u * c) + east0 / spacing
            cell_n, cell_e = np.floor(gn), np.floor(ge)
            checker = (cell_n + cell_e).astype(np.int32) & 1
            gn -= cell_n
            ge -= cell_e
            np.minimum(gn, 1 - gn, out=gn)  # distance to the nearest grid line
            np.minimum(ge, 1 - ge, out=ge)
            np.minimum(gn, ge, out=gn)
            # a line is ~1.2 pixel wide: one pixel spans d/f metres at that row
            line = gn < (1.2 * d / (f * spacing))[:, None]
            # Colour by palette lookup (row, checker, line): a flat np.take is several
            # times faster than per-pixel blending or fancy 2-D indexing.
            fog = np.clip(d / (cam_h * 25.0 + 30.0), 0, 1)[:, None]
            pal = np.empty((h - hz, 4, 3), dtype=np.float32)
            scene = self._scene
            pal[:, 0] = scene.near
            pal[:, 1] = scene.near * 0.9
            pal[:, 2:] = scene.grid
            pal = pal * (1 - fog[:, :, None]) + scene.far * fog[:, :, None]
            index = checker + 2 * line + 4 * np.arange(h - hz, dtype=np.int32)[:, None]
            img[hz:] = np.take(pal.astype(np.uint8).reshape(-1, 3), index, axis=0)

            self._draw_obstacles(img, pose, horizon, cam_h, north0, east0, psi)

        # Overlays: heading at the top, counter and time of day at the bottom.
        block, _ = _code_layout(w)
        digit_h = max(16, h // 12)
        draw_text(
            img,
            f"{round(heading) % 360:03d}",
            w // 2 - digit_h,
            2 * block + 6,
            digit_h,
            (255, 255, 255),
        )
        big = max(20, h // 10)
        box_top = h - big - 12
        np.right_shift(img[box_top:], 2, out=img[box_top:])  # darken behind the digits
        x = draw_text(img, f"{counter % 1_000_000:06d}", 10, box_top + 6, big, (255, 255, 80))
        clock = time.strftime("%H:%M:%S", time.gmtime(ts_ms / 1000)) + f".{ts_ms % 1000:03d}"
        draw_text(img, clock, x + big // 2, box_top + 6, big, (255, 255, 255))
        stamp_frame_code(img, counter, ts_ms)
        return img

    def _sky(self, horizon: int) -> RGB:
        """The sky gradient for a horizon row, cached: the horizon moves only with tilt,
        and copying a ready image is far cheaper than broadcasting row colours."""
        if self._sky_cache is None or self._sky_cache[0] != horizon:
            y = np.arange(self.height, dtype=np.float32)
            k = np.clip((horizon - y) / (0.6 * self.height), 0, 1)[:, None]
            rows = (_SKY_HORIZON * (1 - k) + _SKY_TOP * k).astype(np.uint8)
            sky = np.ascontiguousarray(
                np.broadcast_to(rows[:, None, :], (self.height, self.width, 3))
            )
            self._sky_cache = (horizon, sky)
        return self._sky_cache[1]

    def _draw_obstacles(
        self,
        img: RGB,
        pose: CameraPose,
        horizon: int,
        cam_h: float,
        north0: float,
        east0: float,
        psi: float,
    ) -> None:
        if not pose.obstacles or self._origin is None:
            return
        f, w, h = self._focal, self.width, self.height
        c, s = math.cos(psi), math.sin(psi)
        seen = []
        for lat, lon, radius, height in pose.obstacles:
            on, oe = local_offset_m(self._origin, (lat, lon))
            dn, de = on - north0, oe - east0
            fwd, right = dn * c + de * s, -dn * s + de * c
            if fwd > 0.3:
                seen.append((fwd, right, radius, height))
        for fwd, right, radius, height in sorted(seen, reverse=True):  # far first
            xc = w / 2 + f * right / fwd
            half = max(1.0, f * radius / fwd)
            x0, x1 = int(max(0, xc - half)), int(min(w, xc + half))
            y1 = int(min(h, horizon + f * cam_h / fwd))
            y0 = int(max(0, horizon - f * (height - cam_h) / fwd))
            if x0 < x1 and y0 < y1:
                shade = max(0.35, min(1.0, 6.0 / fwd))
                img[y0:y1, x0:x1] = (int(235 * shade), int(120 * shade), int(30 * shade))
                img[y0:y1, x0 : min(x1, x0 + 2)] = (60, 30, 10)
                img[y0:y1, max(x0, x1 - 2) : x1] = (60, 30, 10)


class V4L2Camera:
    """A Linux V4L2 camera (USB webcam, Raspberry Pi camera through its V4L2 driver or
    ``libcamerify``), read with aiortc's ``MediaPlayer(format="v4l2")``.

    The device is opened on the first ``frame()`` and released by ``close()``, so the
    camera is off while nobody watches. ``input_format`` picks the camera's pixel format
    (``"mjpeg"`` lets cheap webcams reach 30 fps; ``"yuyv422"`` avoids a JPEG decode).
    Not exercised by the test suite (no device); see docs/video.md.
    """

    def __init__(
        self,
        device: str = "/dev/video0",
        *,
        width: int = 640,
        height: int = 480,
        fps: float = 15.0,
        input_format: str | None = None,
    ) -> None:
        self.device = device
        self.options = {"video_size": f"{width}x{height}", "framerate": f"{fps:g}"}
        if input_format:
            self.options["input_format"] = input_format
        self._track: MediaStreamTrack | None = None

    async def frame(self) -> av.VideoFrame:
        """The camera's next frame; raises VideoError when the device cannot be opened."""
        if self._track is None:
            from aiortc.contrib.media import MediaPlayer

            try:
                # Opening a V4L2 device blocks (format negotiation): keep it off the loop.
                player = await asyncio.to_thread(
                    MediaPlayer, self.device, format="v4l2", options=dict(self.options)
                )
            except (OSError, av.FFmpegError) as exc:
                raise VideoError(f"cannot open camera {self.device}: {exc}") from exc
            if player.video is None:
                raise VideoError(f"{self.device} has no video stream")
            self._track = player.video
        frame = await self._track.recv()
        # MediaPlayer queues every captured frame without bound; when the encoder fell
        # behind, skip to the newest so latency does not build up. (Private attribute,
        # hence the guard: without it we merely lose the skipping.)
        queue = getattr(self._track, "_queue", None)
        if isinstance(queue, asyncio.Queue):
            while queue.qsize() > 0:
                newer = queue.get_nowait()
                if newer is None:  # end of stream: leave it for the next recv()
                    queue.put_nowait(newer)
                    break
                frame = newer
        if not isinstance(frame, av.VideoFrame):
            raise VideoError(f"{self.device} gave {type(frame).__name__}, not a video frame")
        return frame

    async def close(self) -> None:
        """Stop the capture thread and close the device (MediaPlayer does both when its
        last track stops; the thread join blocks, hence the worker thread)."""
        track, self._track = self._track, None
        if track is not None:
            await asyncio.to_thread(track.stop)


class MjpegCamera:
    """An HTTP ``multipart/x-mixed-replace`` JPEG stream, as served by an ESP32-CAM
    (``http://<ip>:81/stream``), mjpg-streamer or ``motion``.

    A background task reads the stream (identity or chunked transfer encoding; a part's
    ``Content-Length`` is used when present so a frame is complete without waiting for
    the next boundary) and keeps only the newest JPEG; ``frame()`` waits for a JPEG newer
    than the last one returned and decodes it (PyAV's mjpeg decoder, in a worker thread).
    A lost connection is retried every ``reconnect_s`` until ``close()``; meanwhile
    ``frame()`` waits. Credentials in the URL (``http://user:pass@host/``) are sent as
    HTTP basic auth.
    """

    def __init__(self, url: str, *, timeout_s: float = 10.0, reconnect_s: float = 1.0) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise VideoError(f"MJPEG url must be http(s)://host[:port]/path, not {url!r}")
        self.url = url
        self._parts = parts
        self.timeout_s, self.reconnect_s = timeout_s, reconnect_s
        self._reader: asyncio.Task[None] | None = None
        self._latest: bytes | None = None
        self._seq = 0  # JPEGs received
        self._returned = 0  # seq of the last JPEG returned by frame()
        self._new = asyncio.Event()
        self._decoder: av.VideoCodecContext | None = None
        #: JPEGs received and decoded so far (for tests and diagnostics)
        self.jpegs_received = 0
        self.frames_decoded = 0

    async def frame(self) -> av.VideoFrame:
        """Decode and return the newest JPEG not yet returned (older ones are skipped:
        latency beats completeness for remote driving)."""
        if self._reader is None or self._reader.done():
            self._reader = asyncio.create_task(self._run(), name=f"mjpeg {self.url}")
        while True:
            while self._seq == self._returned:
                self._new.clear()
                await self._new.wait()
            jpeg, self._returned = self._latest, self._seq
            assert jpeg is not None
            frame = await asyncio.to_thread(self._decode, jpeg)
            if frame is not None:
                self.frames_decoded += 1
                return frame

    def _decode(self, jpeg: bytes) -> av.VideoFrame | None:
        if self._decoder is None:
            self._decoder = av.CodecContext.create("mjpeg", "r")
        try:
            frames = self._decoder.decode(av.Packet(jpeg))
        except av.FFmpegError as exc:
            logger.warning("MJPEG %s: undecodable JPEG skipped (%s)", self.url, exc)
            return None
        for f in frames:
            if isinstance(f, av.VideoFrame):
                return f
        return None

    async def close(self) -> None:
        """Stop reading (closes the HTTP connection)."""
        task, self._reader = self._reader, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._latest = None
        self._returned = self._seq

    async def _run(self) -> None:
        while True:
            try:
                await self._read_stream()
                logger.warning("MJPEG %s: stream ended; reconnecting", self.url)
            except (OSError, asyncio.IncompleteReadError, TimeoutError, VideoError) as exc:
                logger.warning("MJPEG %s: %s; reconnecting", self.url, exc)
            await asyncio.sleep(self.reconnect_s)

    async def _read_stream(self) -> None:
        p = self._parts
        port = p.port or (443 if p.scheme == "https" else 80)
        reader, writer = await _within(
            self.timeout_s, asyncio.open_connection(p.hostname, port, ssl=p.scheme == "https")
        )
        try:
            path = urllib.parse.urlunsplit(("", "", p.path or "/", p.query, ""))
            head = [f"GET {path} HTTP/1.1", f"Host: {p.netloc.rpartition('@')[2]}"]
            if p.username is not None:
                cred = (
                    f"{urllib.parse.unquote(p.username)}:{urllib.parse.unquote(p.password or '')}"
                )
                head.append("Authorization: Basic " + base64.b64encode(cred.encode()).decode())
            head += ["Accept: multipart/x-mixed-replace", "Connection: close", "", ""]
            writer.write("\r\n".join(head).encode())
            await writer.drain()
            status = await _within(self.timeout_s, reader.readline())
            if len(status.split()) < 2 or status.split()[1] != b"200":
                raise VideoError(f"HTTP status {status.decode(errors='replace').strip()!r}")
            headers = await _read_headers(reader, self.timeout_s)
            ctype = headers.get("content-type", "")
            boundary = _multipart_boundary(ctype)
            chunked = "chunked" in headers.get("transfer-encoding", "").lower()
            body = _http_body(reader, chunked, self.timeout_s)
            async for jpeg in _multipart_jpegs(body, boundary):
                self._latest = jpeg
                self._seq += 1
                self.jpegs_received += 1
                self._new.set()
        finally:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


async def _within(timeout_s: float, aw: Awaitable[_T]) -> _T:
    """``await aw`` with a time limit (TimeoutError). Not asyncio.wait_for: on Python
    3.11 it swallows a cancellation that arrives as ``aw`` completes, and a reader task
    that ignores its cancellation would never let ``close()`` return."""
    async with asyncio.timeout(timeout_s):
        return await aw


async def _read_headers(reader: asyncio.StreamReader, timeout_s: float) -> dict[str, str]:
    headers: dict[str, str] = {}
    while True:
        line = await _within(timeout_s, reader.readline())
        if not line:
            raise VideoError("connection closed in the HTTP headers")
        if line in (b"\r\n", b"\n"):
            return headers
        name, _, value = line.decode("latin-1").partition(":")
        headers[name.strip().lower()] = value.strip()


def _multipart_boundary(content_type: str) -> bytes:
    kind, _, params = content_type.partition(";")
    if not kind.strip().lower().startswith("multipart/"):
        raise VideoError(f"not an MJPEG stream (Content-Type {content_type!r})")
    for param in params.split(";"):
        name, _, value = param.strip().partition("=")
        if name.lower() == "boundary" and value.strip('"'):
            # Some servers put the leading "--" in the parameter, some do not; the
            # delimiter is searched without it so both work.
            return value.strip('"').removeprefix("--").encode("latin-1")
    raise VideoError("multipart stream without a boundary")


async def _http_body(
    reader: asyncio.StreamReader, chunked: bool, timeout_s: float
) -> AsyncIterator[bytes]:
    """The response body as it arrives, with chunked transfer coding removed."""
    while True:
        if not chunked:
            data = await _within(timeout_s, reader.read(65536))
            if not data:
                return
            yield data
            continue
        size_line = await _within(timeout_s, reader.readline())
        if not size_line:  # closed without the final zero-size chunk
            return
        try:
            size = int(size_line.split(b";")[0].strip() or b"x", 16)
        except ValueError as exc:
            raise VideoError(f"bad chunk size {size_line[:20]!r}") from exc
        if size == 0:
            return
        data = await _within(timeout_s, reader.readexactly(size + 2))  # + CRLF
        yield data[:-2]


async def _multipart_jpegs(body: AsyncIterator[bytes], boundary: bytes) -> AsyncIterator[bytes]:
    """JPEGs of a multipart body. A part ends after its Content-Length when given (so
    the frame is out without waiting for the next part), else at the next boundary."""
    buf = b""
    state, length = "boundary", -1
    async for chunk in body:
        buf += chunk
        while True:
            if state == "boundary":
                i = buf.find(boundary)
                end = buf.find(b"\n", i + len(boundary)) if i >= 0 else -1
                if end < 0:
                    buf = buf[-len(boundary) - 64 :] if i < 0 else buf[i:]
                    break
                buf, state = buf[end + 1 :], "headers"
            elif state == "headers":
                if buf.startswith(b"\r\n") or buf.startswith(b"\n"):
                    head, buf = b"", buf[buf.index(b"\n") + 1 :]
                else:
                    i = buf.find(b"\r\n\r\n")
                    if i < 0:
                        if len(buf) > 8192:
                            raise VideoError("multipart part headers too long")
                        break
                    head, buf = buf[:i], buf[i + 4 :]
                length = -1
                for line in head.split(b"\n"):
                    name, _, value = line.partition(b":")
                    if name.strip().lower() == b"content-length":
                        with contextlib.suppress(ValueError):
                            length = int(value.strip())
                state = "body"
            else:
                if length >= 0:
                    if len(buf) < length:
                        break
                    part, buf = buf[:length], buf[length:]
                else:
                    i = buf.find(boundary)
                    if i < 0:
                        break
                    part, buf = buf[:i], buf[i:]
                state = "boundary"
                # Trim what surrounds the JPEG (CRLF, "--" of the next delimiter).
                start, stop = part.find(b"\xff\xd8"), part.rfind(b"\xff\xd9")
                if 0 <= start < stop:
                    yield part[start : stop + 2]


#: Keys of the agent's ``video`` configuration that configure :class:`VideoService`
#: rather than the source; :func:`video_source_create` ignores them, so one mapping can
#: hold both (see :func:`video_service_create`).
SERVICE_OPTIONS: Final = frozenset({"ice_host_addresses", "bitrate", "keyframe_interval_s"})
#: Options a ``video`` section held when the camera kept connections of its own; where
#: each went, for the message that refuses an old configuration.
MOVED_OPTIONS: Final = {
    "ice_servers": "the webrtc section (webrtc.ice_servers)",
    "max_peers": "the webrtc section (webrtc.max_peers)",
    "answer_timeout_s": "nowhere: the browser offers, the agent answers at once",
}


def video_source_create(
    config: Mapping[str, Any],
    *,
    pose: Callable[[], Any] | None = None,
    sources: Mapping[str, Callable[[Mapping[str, Any]], VideoSource]] | None = None,
) -> VideoSource:
    """Build the source an agent's configuration describes.

    ``{"source": "synthetic", "width": 640, "height": 480, "fps": 15, "scene": "land"}``
    (``pose`` is the callable giving the vehicle's pose; ``scene`` ``"sea"`` for a boat);
    ``{"source": "v4l2", "device": "/dev/video0",
    "width": 640, "height": 480, "fps": 15, "input_format": "mjpeg"}``;
    ``{"source": "mjpeg", "url": "http://192.168.4.1:81/stream"}``. ``sources`` adds
    the agent's sensors that show as video, by name: ``{"source": "thermal", "width":
    640, "height": 480, "box_confidence": 0.6}`` shows the search mission's thermal
    camera (never a second camera), its factory called with the other keys. Keys in
    :data:`SERVICE_OPTIONS` are ignored; other unknown keys, an unknown source or a bad
    value raise VideoError naming them. Nothing is opened until the first frame.
    """
    moved = sorted(set(config) & set(MOVED_OPTIONS))
    if moved:
        raise VideoError(
            "; ".join(f"video.{key} has moved to {MOVED_OPTIONS[key]}" for key in moved)
        )
    options = {k: v for k, v in config.items() if k not in SERVICE_OPTIONS}
    kind = options.pop("source", "synthetic")
    allowed: dict[str, set[str]] = {
        "synthetic": {"width", "height", "fps", "hfov_deg", "mount_height_m", "scene"},
        "v4l2": {"device", "width", "height", "fps", "input_format"},
        "mjpeg": {"url", "timeout_s", "reconnect_s"},
    }
    extra = dict(sources or {})
    if kind not in allowed and kind not in extra:
        known = ", ".join(sorted({*allowed, *extra}))
        raise VideoError(
            f"unknown video source {kind!r} (one of: {known}; a sensor's source needs "
            "its section, e.g. thermal)"
        )
    if kind in allowed:
        unknown = set(options) - allowed[kind]
        if unknown:
            raise VideoError(f"unknown option(s) for {kind} video: {', '.join(sorted(unknown))}")
    try:
        if kind in extra:
            return extra[kind](options)
        if kind == "synthetic":
            return SyntheticCamera(pose=pose, **options)
        if kind == "v4l2":
            return V4L2Camera(**options)
        if "url" not in options:
            raise VideoError("mjpeg video needs a 'url'")
        return MjpegCamera(**options)
    except (TypeError, ValueError) as exc:
        raise VideoError(f"bad {kind} video option: {exc}") from exc


def video_service_create(
    config: Mapping[str, Any],
    *,
    pose: Callable[[], Any] | None = None,
    sources: Mapping[str, Callable[[Mapping[str, Any]], VideoSource]] | None = None,
) -> VideoService:
    """The :class:`VideoService` for an agent's whole ``video`` configuration: the
    source from :func:`video_source_create`, the :data:`SERVICE_OPTIONS` for the
    service. Raises VideoError on a bad configuration."""
    source = video_source_create(config, pose=pose, sources=sources)
    options = {k: v for k, v in config.items() if k in SERVICE_OPTIONS}
    try:
        return VideoService(source, **options)
    except (TypeError, ValueError) as exc:
        raise VideoError(f"bad video option: {exc}") from exc


# --------------------------------------------------------------------------------------
# Shared encoder
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VideoStatus:
    """What the shared encoder sends now: the picture's size, its frame rate (the
    ladder's step, or the camera's own when slower) and the target bitrate (bit/s)."""

    width: int
    height: int
    fps: int
    bitrate: int


class _Subscriber:
    """One viewer's queue of encoded packets. A viewer starts on (and after an overflow
    resumes at) a keyframe: delta frames without their reference are useless to it."""

    QUEUE_FRAMES: Final = 8

    def __init__(self) -> None:
        self.queue: asyncio.Queue[_Packet] = asyncio.Queue(self.QUEUE_FRAMES)
        self.waiting_keyframe = True

    def offer(self, packet: _Packet) -> bool:
        """Queue ``packet``; False when the viewer fell behind and needs a keyframe."""
        if self.waiting_keyframe:
            if not packet.is_keyframe:
                return True
            self.waiting_keyframe = False
        try:
            self.queue.put_nowait(packet)
        except asyncio.QueueFull:
            while not self.queue.empty():
                self.queue.get_nowait()
            self.waiting_keyframe = True
            return False
        return True


class SharedVp8Encoder:
    """Encodes the source's frames once (VP8) for every subscribed viewer.

    Runs a capture task only while there are subscribers. Keyframes are produced on
    request (a viewer joining, PLI/FIR from any viewer, a viewer's queue overflowing;
    at most one every ``min_keyframe_gap_s``) and at least every
    ``keyframe_interval_s``. Counters: ``frames_captured``, ``frames_encoded`` (libvpx
    calls), ``keyframes``.

    The bitrate follows the receivers' estimates through :attr:`rate` (a
    :class:`~agents.video_rate.RateController`; ``bitrate`` is its ceiling and what is
    sent with no estimate), and with it the size and frame rate (its ladder): frames
    are scaled down and skipped here, after capture. :attr:`status` is what is sent
    now; the functions given to :meth:`add_listener` are called when it changes.

    Why VP8: every WebRTC browser must decode it (RFC 7742), PyAV's wheels ship libvpx,
    and aiortc's ``Vp8Encoder.pack`` turns a whole VP8 frame into RTP payloads with no
    codec state per viewer (its picture id is per sender, which is what RTP wants).
    """

    def __init__(
        self,
        source: VideoSource,
        *,
        bitrate: int = 1_000_000,
        keyframe_interval_s: float = 3.0,
        min_keyframe_gap_s: float = 0.25,
    ) -> None:
        self.source = source
        self.bitrate = bitrate
        self.rate = RateController(max_bitrate=bitrate)
        #: What is sent now (None before the first frame).
        self.status: VideoStatus | None = None
        self._listeners: list[Callable[[VideoStatus], None]] = []
        self._source_fps = 0.0  # measured, smoothed
        self.keyframe_interval_s = keyframe_interval_s
        self.min_keyframe_gap_s = min_keyframe_gap_s
        self.frames_captured = 0
        self.frames_encoded = 0
        self.keyframes = 0
        self._subscribers: set[_Subscriber] = set()
        self._task: asyncio.Task[None] | None = None
        self._stopping: asyncio.Task[None] | None = None  # a run closing the source
        self._keyframe_wanted = False
        self._codec: av.VideoCodecContext | None = None

    @property
    def running(self) -> bool:
        """Whether the capture task is running (some viewer is pulling frames)."""
        return self._task is not None and not self._task.done()

    def subscribe(self) -> _Subscriber:
        """Add a viewer (starting capture if it was idle) and ask for a keyframe."""
        sub = _Subscriber()
        self._subscribers.add(sub)
        self.request_keyframe()
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run(self._stopping), name="video encoder")
        return sub

    def unsubscribe(self, sub: _Subscriber) -> None:
        """Remove a viewer; the last one leaving stops capture and closes the source."""
        self._subscribers.discard(sub)
        if not self._subscribers and self._task is not None:
            self._task.cancel()
            self._stopping, self._task = self._task, None

    def add_listener(self, listener: Callable[[VideoStatus], None]) -> None:
        """Call ``listener`` (on the event loop) whenever :attr:`status` changes."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[VideoStatus], None]) -> None:
        """Stop calling ``listener``."""
        with contextlib.suppress(ValueError):
            self._listeners.remove(listener)

    def request_keyframe(self) -> None:
        """Make the next frame (or the first allowed by the gap) a keyframe."""
        self._keyframe_wanted = True

    async def close(self) -> None:
        """Stop capture and wait for the source to be closed."""
        self._subscribers.clear()
        tasks = [t for t in (self._task, self._stopping) if t is not None]
        self._task = self._stopping = None
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)

    async def _run(self, previous: asyncio.Task[None] | None) -> None:
        if previous is not None:  # let the previous run finish closing the source
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait([previous])
        self._codec = None
        t0 = time.monotonic()
        last_key = last_capture = -math.inf
        key_gap = self.min_keyframe_gap_s  # for requested keyframes; see below
        credit = 1.0  # frames the ladder's frame rate allows now (see below)
        try:
            while self._subscribers:
                try:
                    frame = await self.source.frame()
                    self.frames_captured += 1
                    now = time.monotonic()
                    interval, last_capture = now - last_capture, now
                    if interval < 5.0:  # not the first frame (nor one after a stall)
                        fps = 1 / max(interval, 1e-3)
                        self._source_fps += (fps - self._source_fps) * (
                            0.1 if self._source_fps else 1.0
                        )
                    self.rate.tick()
                    rung = self.rate.rung
                    # The ladder's frame rate: each captured frame earns fps x interval
                    # of a frame; one is sent per whole frame earned. A 30 fps camera on
                    # a 20 fps step sends two frames of three, evenly.
                    if rung.fps is not None:
                        credit = min(1.5, credit + rung.fps * min(interval, 1.0))
                        if credit < 0.95:  # a little slack for a camera's jitter
                            continue
                        credit = max(0.0, credit - 1)
                    force = (
                        self._keyframe_wanted and now - last_key >= key_gap
                    ) or now - last_key >= self.keyframe_interval_s
                    if force:
                        self._keyframe_wanted = False
                    pts = int((now - t0) * 90_000)
                    size = fit_size(frame.width, frame.height, rung)
                    bitrate = self.rate.target_bitrate
                    packets = await asyncio.to_thread(
                        self._encode, frame, pts, force, size, bitrate
                    )
                except Exception as exc:
                    # A camera or codec hiccup must not end the viewers' connections:
                    # release the source, wait, and try again with a fresh encoder.
                    logger.warning("video capture failed (%s); retrying in 1 s", exc)
                    with contextlib.suppress(Exception):
                        await self.source.close()
                    self._codec = None
                    await asyncio.sleep(1.0)
                    continue
                self._report(size, rung.fps, bitrate)
                for packet in packets:
                    if packet.is_keyframe:
                        last_key = now
                        self.keyframes += 1
                        # A keyframe is several frames' worth of bits: on a link that
                        # is barely enough, one every quarter second (a lossy viewer's
                        # picture-loss requests) would fill it, lose more packets and
                        # bring more requests: a picture frozen for good. Requested
                        # ones leave the link at least half its time for the rest.
                        key_gap = max(self.min_keyframe_gap_s, 2 * 8 * packet.size / bitrate)
                    for sub in list(self._subscribers):
                        if not sub.offer(packet):
                            self.request_keyframe()
        finally:
            with contextlib.suppress(Exception):
                await self.source.close()

    def _report(self, size: tuple[int, int], rung_fps: float | None, bitrate: int) -> None:
        """Update :attr:`status` and tell the listeners when it changed."""
        if not self._source_fps:
            return  # the first frame: no frame rate measured yet
        fps = round(self._source_fps)
        if rung_fps is not None:
            fps = min(fps, round(rung_fps))
        status = VideoStatus(width=size[0], height=size[1], fps=fps, bitrate=bitrate)
        previous = self.status
        # A camera's measured rate wanders (more so on a busy machine): news only when
        # it moved by a fifth, each message going to every watching user.
        if (
            previous is not None
            and (previous.width, previous.height, previous.bitrate)
            == (status.width, status.height, status.bitrate)
            and abs(previous.fps - fps) < max(2, previous.fps / 5)
        ):
            return
        self.status = status
        for listener in list(self._listeners):
            try:
                listener(status)
            except Exception:  # one listener's bug must not stop the video
                logger.exception("video status listener failed")

    def _encode(
        self,
        frame: av.VideoFrame,
        pts: int,
        force_keyframe: bool,
        size: tuple[int, int],
        bitrate: int,
    ) -> list[_Packet]:
        """Encode one frame at ``size`` and ``bitrate`` (worker thread; the codec is only
        touched from here, one call at a time). Settings follow aiortc's Vp8Encoder:
        real-time, no lag, CBR."""
        if (frame.width, frame.height) != size or frame.format.name != "yuv420p":
            frame = frame.reformat(width=size[0], height=size[1], format="yuv420p")
        codec = self._codec
        # A new size or bitrate starts a new stream with a keyframe, as aiortc's own
        # Vp8Encoder does: FFmpeg's libvpx wrapper takes neither once it is open.
        if codec is not None and (
            (frame.width, frame.height) != (codec.width, codec.height) or codec.bit_rate != bitrate
        ):
            codec = None
        if codec is None:
            codec = av.CodecContext.create("libvpx", "w")
            codec.width, codec.height = frame.width, frame.height
            codec.pix_fmt = "yuv420p"
            codec.time_base = VIDEO_TIME_BASE
            codec.bit_rate = bitrate
            codec.gop_size = 100_000  # keyframes are placed by us (request/interval)
            codec.qmin, codec.qmax = 2, 56
            rate = str(bitrate)
            codec.options = {
                "bufsize": rate,
                # A keyframe at most three average frames (libwebrtc's floor for this
                # libvpx setting): one that overflows a slow link's queue is lost, and
                # asked for again.
                "max-intra-rate": "300",
                "cpu-used": "-6",
                "deadline": "realtime",
                "lag-in-frames": "0",  # one packet out per frame in, no reordering
                "minrate": rate,
                "maxrate": rate,
                "noise-sensitivity": "4",
                "overshoot-pct": "15",
                "partitions": "0",
                "static-thresh": "1",
                "undershoot-pct": "100",
                "error-resilient": "1",  # decodable after a lost packet's frame is skipped
            }
            self._codec = codec
        frame.pts, frame.time_base = pts, VIDEO_TIME_BASE
        frame.pict_type = (
            av.video.frame.PictureType.I if force_keyframe else av.video.frame.PictureType.NONE
        )
        packets = list(codec.encode(frame))
        self.frames_encoded += 1
        for packet in packets:
            # Vp8Encoder.pack reads pts in time_base to make the RTP timestamp.
            packet.pts, packet.time_base = pts, VIDEO_TIME_BASE
        return packets


class _EncodedTrack(MediaStreamTrack):
    """One viewer's video track: yields the shared encoder's packets. Subscribes on the
    first ``recv()`` (the sender only pulls once the connection is up), unsubscribes on
    ``stop()``."""

    kind = "video"

    def __init__(self, encoder: SharedVp8Encoder) -> None:
        super().__init__()
        self._encoder = encoder
        self._sub: _Subscriber | None = None
        #: Called once on stop (the service forgets this viewer's estimate).
        self.on_stop: Callable[[], None] | None = None

    async def recv(self) -> _Packet:
        if self.readyState != "live":
            raise MediaStreamError
        if self._sub is None:
            self._sub = self._encoder.subscribe()
        return await self._sub.queue.get()

    def stop(self) -> None:
        super().stop()
        if self._sub is not None:
            self._encoder.unsubscribe(self._sub)
            self._sub = None
        if self.on_stop is not None:
            self.on_stop()
            self.on_stop = None


# --------------------------------------------------------------------------------------
# Peer connections
# --------------------------------------------------------------------------------------


def _vp8_preferences() -> list[RTCRtpCodecCapability]:
    """VP8 (and its RTX) only: the shared encoder's packets are VP8."""
    caps = RTCRtpSender.getCapabilities("video").codecs
    vp8 = [c for c in caps if c.mimeType.lower() == "video/vp8"]
    rtx = [c for c in caps if c.mimeType.lower() == "video/rtx"]
    return vp8 + rtx


def ice_server(spec: RTCIceServer | Mapping[str, Any] | str) -> RTCIceServer:
    """An ``RTCIceServer`` from its configuration: an object, ``{"urls", "username",
    "credential"}`` or a URL. Raises VideoError naming what is wrong."""
    if isinstance(spec, RTCIceServer):
        return spec
    if isinstance(spec, str):
        return RTCIceServer(urls=spec)
    if not isinstance(spec, Mapping) or "urls" not in spec:
        raise VideoError("an ICE server needs 'urls'")
    return RTCIceServer(
        urls=spec["urls"], username=spec.get("username"), credential=spec.get("credential")
    )


class VideoService:
    """The vehicle's camera for every WebRTC connection, fed by one shared encoder.

    Use as ``async with VideoService(source) as video:``; leaving the block stops
    capture and closes the source (the service owns it). The connections are
    :class:`agents.rtc.RtcPeers`'s: each that asks for video gets the camera with
    :meth:`attach`.

    * ``ice_host_addresses``: the local addresses the connections offer as ICE host
      candidates (``["127.0.0.1"]`` for loopback-only tests); None lets aioice choose
      (all but loopback). RtcPeers uses them unless its own configuration says.
    * ``bitrate``: the shared encoder's target (bit/s); one bitrate for every viewer,
      since they share the stream.
    * ``keyframe_interval_s``: a keyframe at least this often.
    """

    def __init__(
        self,
        source: VideoSource,
        *,
        ice_host_addresses: Sequence[str] | None = None,
        bitrate: int = 1_000_000,
        keyframe_interval_s: float = 3.0,
    ) -> None:
        self.encoder = SharedVp8Encoder(
            source, bitrate=bitrate, keyframe_interval_s=keyframe_interval_s
        )
        # A lone address (a common configuration slip) means a list of one.
        if isinstance(ice_host_addresses, str):
            ice_host_addresses = [ice_host_addresses]
        self._ice_hosts = list(ice_host_addresses) if ice_host_addresses is not None else None
        self._closed = False

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    @property
    def frames_encoded(self) -> int:
        """Frames the shared encoder has encoded (once per captured frame, whatever the
        number of viewers)."""
        return self.encoder.frames_encoded

    def attach(self, pc: RTCPeerConnection, *, role: Role = "viewer") -> MediaStreamTrack:
        """Add the camera to ``pc`` (a connection another part of the agent negotiates,
        see :mod:`agents.rtc`): a sendonly VP8 transceiver fed by the shared encoder.
        ``role``: whom it serves (``pilot``, ``sfu`` or ``viewer``), which says whether
        its receiver's bandwidth estimate sets the shared bitrate (the pilot's does;
        without a pilot, the SFU's). Returns its track; stop it when the connection ends
        (the last viewer's stop ends capture)."""
        track = _EncodedTrack(self.encoder)
        transceiver = pc.addTransceiver(track, direction="sendonly")
        transceiver.setCodecPreferences(_vp8_preferences())
        sender = transceiver.sender
        # PLI/FIR from this viewer: aiortc would force a keyframe in the sender's own
        # encoder, which this sender does not use; ask the shared encoder instead.
        sender._send_keyframe = self.encoder.request_keyframe  # type: ignore[method-assign]
        self._handle_feedback(sender, role)
        rate = self.encoder.rate
        track.on_stop = lambda: rate.forget(sender)
        return track

    def _handle_feedback(self, sender: RTCRtpSender, role: Role) -> None:
        """Hand the shared encoder's rate controller every REMB and loss report this
        sender receives, and keep its retransmissions within a
        :class:`RetransmitBudget`.

        aiortc reads REMB only to set the ``target_bitrate`` of the sender's own
        encoder, which this sender never uses (it packetises the shared encoder's
        packets), and it has no public event or statistic for it; and it resends every
        packet a NACK names, however full the link. So this one sender's RTCP handler
        is wrapped: a NACK reaches aiortc with the packets the budget allows (the
        first ones, oldest first as the receiver lists them), everything else exactly
        as before, then a REMB naming the sender's SSRC is read with aiortc's own
        parser, as is the fraction lost of a receiver report about it. No aiortc class is
        changed, and only this instance."""
        rate = self.encoder.rate
        rate.attach(sender, role)
        budget = RetransmitBudget()
        handle = sender._handle_rtcp_packet

        async def handle_rtcp(packet: AnyRtcpPacket) -> None:
            if isinstance(packet, RtcpRtpfbPacket) and packet.fmt == RTCP_RTPFB_NACK:
                packet.lost = packet.lost[: budget.allow(len(packet.lost), rate.target_bitrate)]
            await handle(packet)
            if isinstance(packet, RtcpRrPacket | RtcpSrPacket):
                for report in packet.reports:
                    if report.ssrc == sender._ssrc:
                        rate.loss(sender, report.fraction_lost / 256)
            elif isinstance(packet, RtcpPsfbPacket) and packet.fmt == RTCP_PSFB_APP:
                try:
                    bitrate, ssrcs = unpack_remb_fci(packet.fci)
                except ValueError:  # another application-layer feedback than REMB
                    return
                if sender._ssrc in ssrcs:
                    rate.estimate(sender, bitrate)

        sender._handle_rtcp_packet = handle_rtcp  # type: ignore[method-assign]

    @property
    def ice_host_addresses(self) -> list[str] | None:
        """The local addresses ICE may offer (None: aioice's choice)."""
        return self._ice_hosts

    async def close(self) -> None:
        """Stop capture and close the source. Idempotent."""
        if self._closed:
            return
        self._closed = True
        await self.encoder.close()
        await self.encoder.source.close()
