"""Where the vehicle's pictures come from (:class:`VideoSource`): :class:`SyntheticCamera`
draws a scene from the vehicle's pose with a frame code (:mod:`agents.video.framecode`);
:class:`V4L2Camera` reads a Linux camera (Raspberry Pi camera, USB webcam);
:class:`MjpegCamera` reads an HTTP MJPEG stream (ESP32-CAM). A mission's sensor may add
its own (the search mission's thermal camera, :mod:`agents.missions.search.video`).
:func:`video_source_create` builds one from the agent's configuration.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import logging
import math
import time
import urllib.parse
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, NamedTuple, Protocol, TypeVar, runtime_checkable

import av
import av.video.frame
import numpy as np
import numpy.typing as npt
from aiortc import MediaStreamTrack

from agents.geo import local_offset_m
from agents.video import VideoError
from agents.video.framecode import RGB, code_layout, draw_text, stamp_frame_code

_T = TypeVar("_T")

logger = logging.getLogger(__name__)


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
        code_layout(width)  # raises when too narrow for the code rows
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
        block, _ = code_layout(w)
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
SERVICE_OPTIONS: Final = frozenset(
    {
        "ice_host_addresses",
        "bitrate",
        "keyframe_interval_s",
        "codec",
        "encoder",
        "encoder_options",
    }
)
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
