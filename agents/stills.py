"""Still photos for missions: the camera a mission photographs with, and the JPEG it
makes, geotagged.

The agent's configuration says which camera that is, in its ``photo`` section (the
``video`` section is what users watch; a mission mapping an area photographs straight
down with its own camera, often not the one streamed):

    "photo": {"source": "nadir", "hfov_deg": 73.7, "width": 1024, "height": 768}
    "photo": {"source": "v4l2", "device": "/dev/video2", "hfov_deg": 73.7,
              "width": 1920, "height": 1080, "input_format": "mjpeg"}

``hfov_deg``, ``width`` and ``height`` are the camera's optics (the vehicle declares the
same on the platform, ``camera_hfov_deg``, ``camera_width_px``, ``camera_height_px``,
which plans the pictures); ``quality`` (1-95, default 85) the JPEG's.

* ``nadir``: a simulated camera looking straight down, its picture's top towards the
  vehicle's heading. It draws :func:`ground_rgb`, a ground that is a fixed function of
  latitude and longitude (fields, hedges, tracks), so that pictures taken from
  anywhere fit together into one map and a test can tell where a pixel of a mosaic
  came from.
* ``v4l2``: one frame from a V4L2 device, opened for each picture (a camera that
  streams nothing between pictures draws no power and holds no device).

A photo (:class:`Photo`) is its JPEG, with the position, altitude (above home), heading
and time in its EXIF GPS tags, and the same as ``meta`` (what travels beside it to the
platform, agents.artifacts).
"""

from __future__ import annotations

import asyncio
import io
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Protocol, Self

import numpy as np
import numpy.typing as npt

from agents.geo import EARTH_RADIUS_M

#: The agent configuration's section naming the camera missions photograph with.
PHOTO_SECTION: Final = "photo"
SOURCES: Final = ("nadir", "v4l2")
OPTIONS: Final = frozenset(
    {"source", "hfov_deg", "width", "height", "quality", "device", "input_format"}
)
MAX_PIXELS: Final = 50_000_000
#: A picture taken on the ground still sees this much (the simulated camera).
MIN_ALTITUDE_M: Final = 0.5

RGB = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class Photo:
    """A picture: ``jpeg`` (geotagged in its EXIF) and ``meta``: ``lat``, ``lon``,
    ``alt`` (m above home), ``heading_deg``, ``t`` (Unix seconds), ``width``,
    ``height``, ``hfov_deg``."""

    jpeg: bytes
    meta: dict[str, Any]


class StillCamera(Protocol):
    """A camera a mission photographs with; an async context manager the agent holds
    open for its whole life."""

    hfov_deg: float
    width: int
    height: int

    async def capture(self, pose: Mapping[str, Any]) -> Photo:
        """A picture now, taken where ``pose`` says the vehicle is (``lat``, ``lon``,
        ``alt``, ``heading_deg``). Raises OSError when the camera cannot take one."""
        ...


def photo_options_check(options: Mapping[str, Any]) -> None:
    """Validate a ``photo`` section without opening anything. Raises ValueError naming
    the key."""
    unknown = sorted(set(options) - OPTIONS)
    if unknown:
        raise ValueError(f"photo.{unknown[0]}: unknown option")
    if options.get("source") not in SOURCES:
        raise ValueError(f"photo.source: must be one of {', '.join(SOURCES)}")
    hfov = options.get("hfov_deg")
    if isinstance(hfov, bool) or not isinstance(hfov, int | float) or not 1 <= hfov <= 170:
        raise ValueError("photo.hfov_deg: must be a number from 1 to 170")
    for key in ("width", "height"):
        value = options.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or not 16 <= value <= 20_000:
            raise ValueError(f"photo.{key}: must be a whole number of pixels from 16 to 20000")
    if int(options["width"]) * int(options["height"]) > MAX_PIXELS:
        raise ValueError(f"photo.width: more than {MAX_PIXELS} pixels in all")
    quality = options.get("quality", 85)
    if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 95:
        raise ValueError("photo.quality: must be a whole number from 1 to 95")
    if options["source"] == "v4l2":
        if not isinstance(options.get("device"), str) or not options["device"]:
            raise ValueError("photo.device: the V4L2 device's path is required")
        if not isinstance(options.get("input_format", ""), str):
            raise ValueError("photo.input_format: must be text")
    elif "device" in options or "input_format" in options:
        raise ValueError("photo.device: only a v4l2 camera has a device")


def still_camera_create(options: Mapping[str, Any]) -> NadirSimCamera | V4L2StillCamera:
    """The camera a ``photo`` section describes (checked by :func:`photo_options_check`;
    raises ValueError naming the key)."""
    photo_options_check(options)
    hfov, width, height = float(options["hfov_deg"]), int(options["width"]), int(options["height"])
    quality = int(options.get("quality", 85))
    if options["source"] == "nadir":
        return NadirSimCamera(hfov_deg=hfov, width=width, height=height, quality=quality)
    return V4L2StillCamera(
        str(options["device"]),
        input_format=options.get("input_format") or None,
        hfov_deg=hfov,
        width=width,
        height=height,
        quality=quality,
    )


# --- the simulated ground ------------------------------------------------------------------

#: The fields' size, the hedges' width, the tracks' spacing and width, the crop rows'
#: spacing (metres).
FIELD_M: Final = 40.0
HEDGE_M: Final = 1.2
TRACK_EVERY_M: Final = 240.0
TRACK_M: Final = 5.0
ROW_M: Final = 3.0
_FIELDS: Final = np.array(
    [
        [118, 148, 62],  # pasture
        [176, 160, 84],  # stubble
        [92, 122, 48],  # maize
        [150, 110, 70],  # ploughed
        [196, 182, 110],  # wheat
        [70, 104, 60],  # woodland
    ],
    dtype=np.float32,
)
_HEDGE: Final = np.array([46, 70, 38], dtype=np.float32)
_TRACK: Final = np.array([168, 158, 146], dtype=np.float32)


def _mix(a: npt.NDArray[np.int64], b: npt.NDArray[np.int64]) -> npt.NDArray[np.uint64]:
    """A well-mixed hash of two integer grids (the same cell, the same value, anywhere)."""
    h = a.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) ^ b.astype(np.uint64) * np.uint64(
        0xC2B2AE3D27D4EB4F
    )
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    return h


def ground_metres(
    lat: npt.ArrayLike, lon: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The ground's own (north, east) coordinates, in metres, of points in degrees."""
    lat_r = np.radians(np.asarray(lat, dtype=np.float64))
    lon_r = np.radians(np.asarray(lon, dtype=np.float64))
    return lat_r * EARTH_RADIUS_M, lon_r * EARTH_RADIUS_M * np.cos(lat_r)


def ground_rgb(lat: npt.ArrayLike, lon: npt.ArrayLike) -> RGB:
    """The simulated ground's colour at each point (degrees; any shape ``S``): an
    ``S + (3,)`` array of RGB. Fields of :data:`FIELD_M` with crop rows, hedges
    between them, a track every :data:`TRACK_EVERY_M` north-south and east-west."""
    north, east = ground_metres(lat, lon)
    cx = np.floor(east / FIELD_M).astype(np.int64)
    cy = np.floor(north / FIELD_M).astype(np.int64)
    h = _mix(cx, cy)
    colour = _FIELDS[(h % np.uint64(len(_FIELDS))).astype(np.intp)]
    shade = 0.85 + 0.3 * ((h >> np.uint64(8)) % np.uint64(64)).astype(np.float32) / 63.0
    colour = colour * shade[..., None]
    # Crop rows, along the field's length: east-west or north-south as the hash says.
    along = np.where((h >> np.uint64(16)) % np.uint64(2) == 0, north, east)
    rows = np.mod(along, ROW_M) < ROW_M / 3
    colour = np.where(rows[..., None], colour * 0.8, colour)
    ex, ny = np.mod(east, FIELD_M), np.mod(north, FIELD_M)
    hedge = (np.minimum(ex, FIELD_M - ex) < HEDGE_M / 2) | (
        np.minimum(ny, FIELD_M - ny) < HEDGE_M / 2
    )
    colour = np.where(hedge[..., None], _HEDGE, colour)
    tx, ty = np.mod(east, TRACK_EVERY_M), np.mod(north, TRACK_EVERY_M)
    track = (np.minimum(tx, TRACK_EVERY_M - tx) < TRACK_M / 2) | (
        np.minimum(ty, TRACK_EVERY_M - ty) < TRACK_M / 2
    )
    colour = np.where(track[..., None], _TRACK, colour)
    return np.clip(colour, 0, 255).astype(np.uint8)


def nadir_lat_lon(
    pose: Mapping[str, Any], *, hfov_deg: float, width: int, height: int
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Where each pixel's centre of a nadir picture taken at ``pose`` is on flat ground
    at home's level: ``(lat, lon)`` arrays of shape ``(height, width)``. The picture's
    top is towards the heading; the inverse of this is how a mosaic places it."""
    alt = max(float(pose.get("alt") or 0.0), MIN_ALTITUDE_M)
    gsd = 2 * alt * math.tan(math.radians(hfov_deg) / 2) / width
    heading = math.radians(float(pose.get("heading_deg") or 0.0))
    u = (np.arange(width, dtype=np.float64) + 0.5 - width / 2) * gsd  # to the right
    v = (height / 2 - np.arange(height, dtype=np.float64) - 0.5) * gsd  # ahead
    right, ahead = np.meshgrid(u, v)
    east = right * math.cos(heading) + ahead * math.sin(heading)
    north = -right * math.sin(heading) + ahead * math.cos(heading)
    lat0, lon0 = float(pose["lat"]), float(pose["lon"])
    lat = lat0 + np.degrees(north / EARTH_RADIUS_M)
    lon = lon0 + np.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return lat, lon


# --- the photo -----------------------------------------------------------------------------


def _dms(value: float) -> tuple[float, float, float]:
    value = abs(value)
    degrees = math.floor(value)
    minutes = math.floor((value - degrees) * 60)
    seconds = (value - degrees - minutes / 60) * 3600
    return (float(degrees), float(minutes), round(seconds, 4))


def photo_jpeg(rgb: RGB, meta: Mapping[str, Any], *, quality: int = 85) -> bytes:
    """``rgb`` as a JPEG whose EXIF GPS tags say where (``lat``, ``lon``), how high
    (``alt``) and which way (``heading_deg``) it was taken, and when (``t``)."""
    from PIL import ExifTags, Image

    exif = Image.Exif()
    when = time.gmtime(float(meta["t"]))
    exif[ExifTags.Base.DateTime] = time.strftime("%Y:%m:%d %H:%M:%S", when)
    lat, lon = float(meta["lat"]), float(meta["lon"])
    gps: dict[int, Any] = {
        ExifTags.GPS.GPSVersionID: b"\x02\x03\x00\x00",
        ExifTags.GPS.GPSLatitudeRef: "N" if lat >= 0 else "S",
        ExifTags.GPS.GPSLatitude: _dms(lat),
        ExifTags.GPS.GPSLongitudeRef: "E" if lon >= 0 else "W",
        ExifTags.GPS.GPSLongitude: _dms(lon),
        ExifTags.GPS.GPSTimeStamp: (float(when.tm_hour), float(when.tm_min), float(when.tm_sec)),
        ExifTags.GPS.GPSDateStamp: time.strftime("%Y:%m:%d", when),
    }
    if meta.get("alt") is not None:
        # Above home, not the sea: GPSAltitudeRef has no such reference, so it is
        # given as is (meta says what it is).
        gps[ExifTags.GPS.GPSAltitudeRef] = b"\x00"
        gps[ExifTags.GPS.GPSAltitude] = round(abs(float(meta["alt"])), 2)
    if meta.get("heading_deg") is not None:
        gps[ExifTags.GPS.GPSImgDirectionRef] = "T"
        gps[ExifTags.GPS.GPSImgDirection] = round(float(meta["heading_deg"]) % 360, 2)
    exif[ExifTags.IFD.GPSInfo] = gps
    out = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(out, "JPEG", quality=quality, exif=exif)
    return out.getvalue()


def _meta(pose: Mapping[str, Any], camera: StillCamera, t: float) -> dict[str, Any]:
    def number(key: str, digits: int) -> float | None:
        value = pose.get(key)
        return None if value is None else round(float(value), digits)

    return {
        "lat": number("lat", 7),
        "lon": number("lon", 7),
        "alt": number("alt", 2),
        "heading_deg": number("heading_deg", 1),
        "t": round(t, 3),
        "width": camera.width,
        "height": camera.height,
        "hfov_deg": camera.hfov_deg,
    }


class _Camera:
    def __init__(self, *, hfov_deg: float, width: int, height: int, quality: int) -> None:
        self.hfov_deg = hfov_deg
        self.width = width
        self.height = height
        self.quality = quality

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        return None

    async def capture(self, pose: Mapping[str, Any]) -> Photo:
        if pose.get("lat") is None or pose.get("lon") is None:
            raise OSError("no position to tag the photo with")
        t = time.time()
        meta = _meta(pose, self, t)
        rgb = await self._frame(pose)
        jpeg = await asyncio.to_thread(photo_jpeg, rgb, meta, quality=self.quality)
        return Photo(jpeg=jpeg, meta=meta)

    async def _frame(self, pose: Mapping[str, Any]) -> RGB:
        raise NotImplementedError


class NadirSimCamera(_Camera):
    """The simulated downward camera (module docstring)."""

    async def _frame(self, pose: Mapping[str, Any]) -> RGB:
        return await asyncio.to_thread(self.render, pose)

    def render(self, pose: Mapping[str, Any]) -> RGB:
        """The picture from ``pose`` (``lat``, ``lon``, ``alt``, ``heading_deg``)."""
        lat, lon = nadir_lat_lon(pose, hfov_deg=self.hfov_deg, width=self.width, height=self.height)
        return ground_rgb(lat, lon)


class V4L2StillCamera(_Camera):
    """One frame of a V4L2 device per picture (module docstring). Not exercised by the
    test suite (no device)."""

    #: Frames read and thrown away first: a camera just opened is still finding its
    #: exposure.
    SETTLE_FRAMES: Final = 5

    def __init__(
        self,
        device: str,
        *,
        input_format: str | None = None,
        hfov_deg: float,
        width: int,
        height: int,
        quality: int,
    ) -> None:
        super().__init__(hfov_deg=hfov_deg, width=width, height=height, quality=quality)
        self.device = device
        self.options = {"video_size": f"{self.width}x{self.height}"}
        if input_format:
            self.options["input_format"] = input_format

    async def _frame(self, pose: Mapping[str, Any]) -> RGB:
        return await asyncio.to_thread(self._grab)

    def _grab(self) -> RGB:
        import av

        try:
            container = av.open(self.device, format="v4l2", options=dict(self.options))
        except (OSError, av.FFmpegError) as exc:
            raise OSError(f"cannot open camera {self.device}: {exc}") from exc
        try:
            for count, frame in enumerate(container.decode(video=0)):
                if count >= self.SETTLE_FRAMES:
                    return np.asarray(frame.to_ndarray(format="rgb24"), dtype=np.uint8)
        except av.FFmpegError as exc:
            raise OSError(f"camera {self.device}: {exc}") from exc
        finally:
            container.close()
        raise OSError(f"camera {self.device} gave no picture")
