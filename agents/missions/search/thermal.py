"""Thermal camera and person-in-water detection: what the search mission alone needs.

A search drone looks straight down (nadir) with a small radiometric thermal camera
(default: FLIR Lepton 3.5, 160x120 pixels, 57 degree horizontal field of view, ~9 fps).
Frames are float32 arrays of temperatures in degrees Celsius (H x W).

* Sources (:class:`ThermalSource`): :class:`SyntheticSeaThermal` renders the sea under
  the vehicle's pose with persons, boats and sun-glint patches from a scene description
  (demos and tests); :class:`V4L2Thermal` reads a UVC thermal camera delivering Y16
  (a Lepton on a PureThermal board) through PyAV. :func:`thermal_source_create` builds
  one from the agent's ``thermal`` configuration (the search mission's sensor).
* :class:`ThermalFeed` owns the agent's one source and shares its frames: the search
  runner (detection) and the video (false colour) both read it, and each frame is
  captured and analysed once, whoever asks.
* :func:`detect_persons` finds warm, person-sized blobs against the water
  (thresholds and their reasons in :class:`DetectorSettings`); :func:`geolocate`
  turns a blob's pixel position into latitude and longitude.
* :func:`false_colour` draws a frame in an ironbow palette with boxes round the
  detections, for :class:`agents.missions.search.video.ThermalVideo`.

Everything but :class:`V4L2Thermal` is numpy only; docs/rescue-agent.md has the
algorithm, its figures and its limits.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from types import TracebackType
from typing import Any, Final, Protocol, Self, TypeAlias

import numpy as np
import numpy.typing as npt

from agents.geo import local_offset_m, offset

__all__ = [
    "DEFAULT_DETECTOR",
    "IRONBOW",
    "Blob",
    "DetectorSettings",
    "SyntheticSeaThermal",
    "ThermalError",
    "ThermalFeed",
    "ThermalFrame",
    "ThermalPose",
    "ThermalSource",
    "V4L2Thermal",
    "colour_range",
    "detect_persons",
    "false_colour",
    "footprint_m",
    "geolocate",
    "ground_sample_distance_m",
    "thermal_config_check",
    "thermal_feed_create",
    "thermal_source_create",
    "y16_to_celsius",
]

Celsius: TypeAlias = npt.NDArray[np.float32]
RGB: TypeAlias = npt.NDArray[np.uint8]

#: FLIR Lepton 3.5: 160x120 pixels, 57 degrees horizontal field of view, 8.7 Hz.
DEFAULT_WIDTH: Final = 160
DEFAULT_HEIGHT: Final = 120
DEFAULT_HFOV_DEG: Final = 57.0
DEFAULT_FPS: Final = 9.0
#: Below this height above the water the camera sees nothing useful (no GSD).
MIN_ALTITUDE_M: Final = 1.0
KELVIN_OFFSET: Final = 273.15


class ThermalError(Exception):
    """The thermal camera could not deliver a frame (device missing, wrong mode)."""


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ThermalPose:
    """Where the camera was when a frame was taken: position, height above the water
    (None: unknown or on the ground) and heading in degrees clockwise from north. The
    camera looks straight down; the top of the image is the vehicle's nose."""

    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    heading_deg: float = 0.0

    @classmethod
    def coerce(cls, value: Any, *, alt_offset_m: float = 0.0) -> ThermalPose:
        """From a ThermalPose, a mapping (``lat``, ``lon``, ``alt``, ``heading_deg`` or
        ``heading``; what ``Agent._camera_pose`` returns) or an object with those
        attributes (the adapter's VehicleState). ``alt_offset_m`` is added to a known
        altitude: the height of the take-off point above the water."""
        if isinstance(value, ThermalPose):
            pose = value
        else:

            def get(*names: str) -> Any:
                for name in names:
                    v = (
                        value.get(name)
                        if isinstance(value, Mapping)
                        else getattr(value, name, None)
                    )
                    if v is not None:
                        return v
                return None

            lat, lon, alt = get("lat"), get("lon"), get("alt")
            heading = get("heading_deg", "heading")
            pose = cls(
                lat=None if lat is None else float(lat),
                lon=None if lon is None else float(lon),
                alt=None if alt is None else float(alt),
                heading_deg=float(heading or 0.0),
            )
        if alt_offset_m and pose.alt is not None:
            pose = cls(pose.lat, pose.lon, pose.alt + alt_offset_m, pose.heading_deg)
        return pose


def footprint_m(alt_m: float, hfov_deg: float, width: int, height: int) -> tuple[float, float]:
    """(width, height) in metres of the water a nadir camera sees from ``alt_m``."""
    across = 2.0 * alt_m * math.tan(math.radians(hfov_deg) / 2.0)
    return across, across * height / width


def ground_sample_distance_m(alt_m: float | None, hfov_deg: float, width: int) -> float | None:
    """Metres of water per pixel at ``alt_m``; None below :data:`MIN_ALTITUDE_M`."""
    if alt_m is None or alt_m < MIN_ALTITUDE_M:
        return None
    return 2.0 * alt_m * math.tan(math.radians(hfov_deg) / 2.0) / width


def _camera_to_ne(right: Any, forward: Any, heading_deg: float) -> tuple[Any, Any]:
    """Camera axes (right, forward of the nose) to (north, east), scalars or arrays."""
    psi = math.radians(heading_deg)
    c, s = math.cos(psi), math.sin(psi)
    return forward * c - right * s, forward * s + right * c


def _ne_to_camera(north: Any, east: Any, heading_deg: float) -> tuple[Any, Any]:
    """(north, east) to camera axes (right, forward); inverse of :func:`_camera_to_ne`."""
    psi = math.radians(heading_deg)
    c, s = math.cos(psi), math.sin(psi)
    return -north * s + east * c, north * c + east * s


def geolocate(
    blob: Blob, pose: ThermalPose, hfov_deg: float, width: int, height: int
) -> tuple[float, float]:
    """(lat, lon) of ``blob``'s centroid seen from ``pose``.

    The offset from the image centre in pixels becomes metres right of and ahead of
    the vehicle through the ground sample distance, is turned by the heading into
    metres north and east, and added to the vehicle's position. Assumes a nadir
    camera over flat water (a gimbal, or a level drone: a tilt of t degrees moves the
    answer by alt * tan(t)). Raises ValueError when the pose has no position or is
    below :data:`MIN_ALTITUDE_M`.
    """
    gsd = ground_sample_distance_m(pose.alt, hfov_deg, width)
    if pose.lat is None or pose.lon is None or gsd is None:
        raise ValueError("geolocation needs the vehicle's position and an altitude above 1 m")
    right = (blob.col - width / 2.0) * gsd
    forward = (height / 2.0 - blob.row) * gsd
    north, east = _camera_to_ne(right, forward, pose.heading_deg)
    return offset((pose.lat, pose.lon), north, east)


# --------------------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectorSettings:
    """Thresholds of :func:`detect_persons`, and why they are what they are.

    * ``k_sigma``, ``min_contrast_c``: a pixel seeds a blob when it is warmer than the
      water by ``max(k_sigma * sigma, min_contrast_c)``, sigma being the frame's robust
      spread (1.4826 * median absolute deviation: waves and sensor noise, not the
      blobs). Open water in the long-wave infrared is uniform to a degree or less
      within one frame, while a head out of the water shows 8-18 degC above it (skin
      30-36 degC, wet hair and clothes a little cooler, against 10-22 degC water). 5
      sigma against rough water and 3 degC at least (10 sigma of a noisy 0.3 degC
      sensor: with 19 200 pixels a frame, pure noise crosses it less than once in
      10^15 frames) leave room for a person only half filling a pixel.
    * ``grow_c``: the blob then grows over 8-connected neighbours warmer than the
      water by ``max(3 * sigma, grow_c)``, to catch the edge pixels a body only
      partly covers (their heat counts in the area below).
    * ``person_c``: nominal apparent temperature of a person in water. A blob's area
      is its **equivalent area**: its excess heat (sum of pixel excess over the local
      water x pixel area) divided by the excess a person would have. Mixing a small
      body into a few pixels conserves that sum, so the estimate holds from 20 m to
      120 m, resolved or not.
    * ``min_area_m2``, ``max_area_m2``: a head alone is ~0.04 m2, head and shoulders
      ~0.25 m2, someone floating face up ~0.7 m2. Below 0.03 m2 is a hot pixel or
      noise; above 1.5 m2 is a boat, a buoy, floating debris or a glint patch.
    * ``max_person_c``: a blob with a pixel above 42 degC is an engine, an exhaust or
      a flare, not skin.
    * ``min_person_c``: a blob resolved well enough that its peak pixel is surely
      covered (at least ``resolved_pixels`` pixels within half its peak contrast) must
      reach 24 degC there; a large lukewarm patch (sun glint, warm foam) does not.
    * ``typical_area_m2``, ``full_contrast_c``: the confidence is the geometric mean of
      a contrast score (peak contrast / ``full_contrast_c``, capped at 1) and a size
      score (a log-normal bump around ``typical_area_m2``, width ``size_spread``).
    """

    k_sigma: float = 5.0
    min_contrast_c: float = 3.0
    grow_c: float = 1.5
    person_c: float = 32.0
    min_area_m2: float = 0.03
    max_area_m2: float = 1.5
    max_person_c: float = 42.0
    min_person_c: float = 24.0
    resolved_pixels: int = 9
    typical_area_m2: float = 0.25
    size_spread: float = 0.9
    full_contrast_c: float = 10.0

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> DetectorSettings:
        """From the ``detection`` section of the thermal config; ValueError names a bad
        or unknown key."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"thermal detection: unknown key(s) {', '.join(sorted(unknown))}")
        values: dict[str, Any] = {}
        for key, value in data.items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"thermal detection.{key}: must be a number")
            values[key] = int(value) if key == "resolved_pixels" else float(value)
        settings = cls(**values)
        if not 0 < settings.min_area_m2 < settings.max_area_m2:
            raise ValueError("thermal detection: need 0 < min_area_m2 < max_area_m2")
        if settings.k_sigma <= 0 or settings.min_contrast_c <= 0 or settings.grow_c <= 0:
            raise ValueError("thermal detection: k_sigma, min_contrast_c, grow_c must be > 0")
        return settings


DEFAULT_DETECTOR: Final = DetectorSettings()


@dataclass(frozen=True)
class Blob:
    """A warm object found by :func:`detect_persons`.

    ``row``/``col``: centroid in pixels, weighted by excess temperature (the image's
    top left corner is (0, 0), a pixel's centre is at +0.5). ``area_m2``: equivalent
    area at the nominal person temperature (see :class:`DetectorSettings`);
    ``footprint_m2``: area of the pixels it covers. ``peak_c``/``mean_c``: its warmest
    and mean pixel; ``background_c``: the water round it. ``box``: (row0, col0, row1,
    col1), end exclusive.
    """

    row: float
    col: float
    pixels: int
    area_m2: float
    footprint_m2: float
    peak_c: float
    mean_c: float
    background_c: float
    confidence: float
    box: tuple[int, int, int, int]

    @property
    def contrast_c(self) -> float:
        return self.peak_c - self.background_c


def _robust_background(frame: Celsius) -> tuple[float, float]:
    """(median, sigma) of the frame; sigma from the median absolute deviation, which a
    few warm pixels do not move."""
    flat = frame.ravel()
    median = float(np.median(flat))
    mad = float(np.median(np.abs(flat - median)))
    return median, 1.4826 * mad


def _component(mask: bytearray, seen: bytearray, start: int, width: int) -> list[int]:
    """Flat indices of the 8-connected component of ``mask`` containing ``start``.

    ``mask`` and ``seen`` are flat byte copies of arrays padded by one pixel of 0 on
    every side, so neighbours never need a bounds check (and bytes index several
    times faster than numpy scalars)."""
    offsets = (-width - 1, -width, -width + 1, -1, 1, width - 1, width, width + 1)
    seen[start] = 1
    todo = deque([start])
    out = []
    while todo:
        i = todo.popleft()
        out.append(i)
        for d in offsets:
            j = i + d
            if mask[j] and not seen[j]:
                seen[j] = 1
                todo.append(j)
    return out


def detect_persons(
    frame_c: Celsius, *, gsd_m: float, settings: DetectorSettings = DEFAULT_DETECTOR
) -> list[Blob]:
    """Warm, person-sized blobs in a nadir thermal frame of water, most confident first.

    1. Background and spread: the frame's median and 1.4826 x MAD.
    2. Seeds: pixels above ``median + max(k_sigma * sigma, min_contrast_c)``; each
       grows (8-connectivity, breadth first) over pixels above ``median + max(3 *
       sigma, grow_c)``.
    3. Per blob: the local water temperature (median of a 3-pixel ring round its box),
       its excess heat and equivalent area, its temperature-weighted centroid, peak
       and mean.
    4. Rejected: equivalent area outside [min_area_m2, max_area_m2]; peak above
       max_person_c; resolved yet colder than min_person_c at its peak.
    5. Confidence in [0, 1] from contrast and size fit.

    ``gsd_m`` is the ground sample distance (metres per pixel). Runs in ~1 ms on a
    160x120 frame of open water (more when large warm areas must be walked).
    """
    if gsd_m <= 0:
        raise ValueError("gsd_m must be positive")
    frame = np.asarray(frame_c, dtype=np.float32)
    if frame.ndim != 2:
        raise ValueError("a thermal frame is a 2-D array of temperatures")
    h, w = frame.shape
    median, sigma = _robust_background(frame)
    seed_level = median + max(settings.k_sigma * sigma, settings.min_contrast_c)
    grow_level = median + max(3.0 * sigma, settings.grow_c)
    seeds = np.flatnonzero(frame > seed_level)
    if seeds.size == 0:
        return []
    pw = w + 2
    grow = np.zeros((h + 2, pw), dtype=bool)
    grow[1:-1, 1:-1] = frame > grow_level
    grow_flat = bytearray(grow.tobytes())
    seen_flat = bytearray(len(grow_flat))
    pixel_area = gsd_m * gsd_m
    blobs = []
    for seed in seeds:
        r, c = divmod(int(seed), w)
        start = (r + 1) * pw + (c + 1)
        if seen_flat[start]:
            continue  # part of a blob already walked
        flat = np.asarray(_component(grow_flat, seen_flat, start, pw))
        rows, cols = flat // pw - 1, flat % pw - 1
        blob = _blob(frame, grow[1:-1, 1:-1], rows, cols, pixel_area, settings)
        if blob is not None:
            blobs.append(blob)
    blobs.sort(key=lambda b: b.confidence, reverse=True)
    return blobs


def _blob(
    frame: Celsius,
    warm: npt.NDArray[np.bool_],
    rows: npt.NDArray[np.intp],
    cols: npt.NDArray[np.intp],
    pixel_area: float,
    s: DetectorSettings,
) -> Blob | None:
    """Measure one component; None when it cannot be a person."""
    h, w = frame.shape
    r0, r1 = int(np.min(rows)), int(np.max(rows)) + 1
    c0, c1 = int(np.min(cols)), int(np.max(cols)) + 1
    # The water right round the blob: robust to a gradient across the frame (a glint
    # nearby, a temperature front) that the global median would miss.
    R0, R1, C0, C1 = max(0, r0 - 3), min(h, r1 + 3), max(0, c0 - 3), min(w, c1 + 3)
    ring = frame[R0:R1, C0:C1][~warm[R0:R1, C0:C1]]
    if ring.size == 0:
        return None  # warm from edge to edge: no water to compare with
    background = float(np.median(ring))
    temps = frame[rows, cols].astype(np.float64)
    excess = np.maximum(temps - background, 0.0)
    heat = float(excess.sum())
    peak = float(np.max(temps))
    contrast = peak - background
    if heat <= 0 or contrast <= 0:
        return None
    area = heat * pixel_area / max(s.person_c - background, 4.0)
    if not s.min_area_m2 <= area <= s.max_area_m2 or peak > s.max_person_c:
        return None
    resolved = int(np.count_nonzero(excess >= 0.5 * contrast)) >= s.resolved_pixels
    if resolved and peak < s.min_person_c:
        return None
    row = float(((rows + 0.5) * excess).sum() / heat)
    col = float(((cols + 0.5) * excess).sum() / heat)
    contrast_score = min(1.0, contrast / s.full_contrast_c)
    size_score = math.exp(-(math.log(area / s.typical_area_m2) ** 2) / (2 * s.size_spread**2))
    return Blob(
        row=row,
        col=col,
        pixels=int(rows.size),
        area_m2=area,
        footprint_m2=rows.size * pixel_area,
        peak_c=peak,
        mean_c=float(temps.mean()),
        background_c=background,
        confidence=math.sqrt(contrast_score * size_score),
        box=(r0, c0, r1, c1),
    )


# --------------------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------------------

PoseFn: TypeAlias = Callable[[], Any]


class ThermalSource(Protocol):
    """A thermal camera. ``capture()`` returns the next frame (degrees Celsius) with the
    pose it was taken from, paced by the source; ``close()`` releases the device and
    is idempotent (the next capture opens it again)."""

    width: int
    height: int
    hfov_deg: float
    fps: float

    async def capture(self) -> tuple[Celsius, ThermalPose]: ...

    async def close(self) -> None: ...


class _Pacer:
    """Spaces calls ``1/fps`` apart without catching up after a stall."""

    def __init__(self, fps: float) -> None:
        self.period = 1.0 / fps
        self.next_t: float | None = None

    async def wait(self) -> None:
        now = time.monotonic()
        if self.next_t is None or self.next_t < now - self.period:
            self.next_t = now
        await asyncio.sleep(max(0.0, self.next_t - now))
        self.next_t += self.period


def _latlon_list(value: Any, name: str, extra: int = 0) -> list[tuple[float, ...]]:
    """``[[lat, lon, *extra numbers], ...]`` validated; ValueError names ``name``."""
    if not isinstance(value, list | tuple):
        raise ValueError(f"thermal {name}: must be a list")
    out = []
    for i, item in enumerate(value):
        if (
            not isinstance(item, list | tuple)
            or len(item) != 2 + extra
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in item)
        ):
            what = "[lat, lon" + "".join(f", n{k}" for k in range(extra)) + "]"
            raise ValueError(f"thermal {name}[{i}]: expected {what} numbers")
        lat, lon = float(item[0]), float(item[1])
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ValueError(f"thermal {name}[{i}]: latitude or longitude out of range")
        if any(not math.isfinite(float(v)) or float(v) <= 0 for v in item[2:]):
            raise ValueError(f"thermal {name}[{i}]: sizes must be positive numbers")
        out.append(tuple(float(v) for v in item))
    return out


# Person model: head and shoulders out of the water, seen from above. The shoulders
# (wet clothes) are a little cooler than the head (skin).
_SHOULDERS_M: Final = (0.30, 0.25)  # semi-axes across, along the body
_HEAD_RADIUS_M: Final = 0.11
_SHOULDER_DROP_C: Final = 2.0
_SUBSAMPLES: Final = 5  # per pixel side, for area coverage


class SyntheticSeaThermal:
    """The sea as a nadir thermal camera at ``pose()`` sees it.

    Water at ``sea_c`` with slow swell (three sinusoids fixed to the water, amplitude
    ``wave_c``) and per-frame sensor noise (``noise_c``, standard deviation); persons
    (head and shoulders, 0.6 x 0.5 m, head at ``person_c``) each mixed into the pixels
    by the fraction of the pixel it covers; optional boats (``[lat, lon, length_m,
    width_m]`` rectangles at ``boat_c``) and sun-glint patches (``[lat, lon, radius_m,
    delta_c]``, diffuse Gaussian warmth). Below 1 m or with no altitude it sees the
    ground: uniform ``ground_c`` plus noise.

    Deterministic for a given ``seed`` and pose sequence. Rendering a 160x120 frame
    takes about a millisecond.
    """

    def __init__(
        self,
        pose: PoseFn,
        *,
        persons: Sequence[Sequence[float]] = (),
        boats: Sequence[Sequence[float]] = (),
        glints: Sequence[Sequence[float]] = (),
        sea_c: float = 16.0,
        person_c: float = 34.0,
        boat_c: float = 26.0,
        ground_c: float = 20.0,
        noise_c: float = 0.3,
        wave_c: float = 0.4,
        seed: int = 1,
        width: int = DEFAULT_WIDTH,
        height: int = DEFAULT_HEIGHT,
        hfov_deg: float = DEFAULT_HFOV_DEG,
        fps: float = DEFAULT_FPS,
        alt_offset_m: float = 0.0,
    ) -> None:
        _check_geometry(width, height, hfov_deg, fps)
        self.width, self.height, self.hfov_deg, self.fps = width, height, hfov_deg, fps
        self._pose = pose
        self.alt_offset_m = alt_offset_m
        self.persons = [(float(p[0]), float(p[1])) for p in persons]
        self.boats = [tuple(float(v) for v in b) for b in boats]
        self.glints = [tuple(float(v) for v in g) for g in glints]
        self.sea_c, self.person_c, self.boat_c = sea_c, person_c, boat_c
        self.ground_c, self.noise_c, self.wave_c = ground_c, noise_c, wave_c
        self._rng = np.random.default_rng(seed)
        scene = np.random.default_rng(seed + 7919)
        # Each person faces a random way; swell from three random directions.
        self._person_yaw = [float(scene.uniform(0, 360)) for _ in self.persons]
        self._waves = [
            (
                2 * math.pi / wavelength,
                float(scene.uniform(0, 2 * math.pi)),
                float(scene.uniform(0, 2 * math.pi)),
            )
            for wavelength in (7.0, 13.0, 23.0)
        ]
        self._origin: tuple[float, float] | None = None
        self._pacer = _Pacer(fps)
        self._t0 = time.monotonic()

    async def capture(self) -> tuple[Celsius, ThermalPose]:
        """The next frame, ``1/fps`` after the previous one (rendered in a thread)."""
        await self._pacer.wait()
        pose = ThermalPose.coerce(self._pose(), alt_offset_m=self.alt_offset_m)
        frame = await asyncio.to_thread(self.render, pose, time.monotonic() - self._t0)
        return frame, pose

    async def close(self) -> None:
        """Nothing to release; restarts pacing."""
        self._pacer.next_t = None

    def render(self, pose: ThermalPose, t: float = 0.0) -> Celsius:
        """One frame (H x W float32, degC) seen from ``pose`` at scene time ``t`` s."""
        h, w = self.height, self.width
        noise = self._rng.standard_normal((h, w), dtype=np.float32) * np.float32(self.noise_c)
        gsd = ground_sample_distance_m(pose.alt, self.hfov_deg, w)
        if gsd is None or pose.lat is None or pose.lon is None:
            return noise + np.float32(self.ground_c)
        if self._origin is None:
            self._origin = (pose.lat, pose.lon)
        n0, e0 = local_offset_m(self._origin, (pose.lat, pose.lon))
        right = (np.arange(w, dtype=np.float32) + 0.5 - w / 2) * gsd
        forward = (h / 2 - np.arange(h, dtype=np.float32) - 0.5) * gsd
        north, east = _camera_to_ne(right[None, :], forward[:, None], pose.heading_deg)
        north, east = north + n0, east + e0
        sea = np.full((h, w), self.sea_c, dtype=np.float32)
        for k, direction, phase in self._waves:
            along = north * math.cos(direction) + east * math.sin(direction)
            sea += np.float32(self.wave_c / 3) * np.sin(k * along + phase + 0.8 * t)
        for g_lat, g_lon, radius, delta in self.glints:
            gn, ge = local_offset_m(self._origin, (g_lat, g_lon))
            spread = (radius / 2.0) ** 2
            sea += np.float32(delta) * np.exp(
                -((north - gn) ** 2 + (east - ge) ** 2) / (2 * spread)
            )
        frame = sea
        for b_lat, b_lon, length, width in self.boats:
            bn, be = local_offset_m(self._origin, (b_lat, b_lon))
            half = (length / 2, width / 2)
            # Boats lie north-south: inside when within half length/width of the centre.
            reach = math.hypot(*half)
            self._mix(frame, pose, gsd, (bn, be), reach, self.boat_c, _box_inside(half))
        for (p_lat, p_lon), yaw in zip(self.persons, self._person_yaw, strict=True):
            pn, pe = local_offset_m(self._origin, (p_lat, p_lon))
            shoulders_c = self.person_c - _SHOULDER_DROP_C
            reach = _SHOULDERS_M[0]
            self._mix(frame, pose, gsd, (pn, pe), reach, shoulders_c, _ellipse_inside(yaw))
            self._mix(frame, pose, gsd, (pn, pe), reach, self.person_c, _disc_inside())
        # The lens spreads each point a little into its neighbours; noise comes after.
        return _blur(frame) + noise

    def _mix(
        self,
        frame: Celsius,
        pose: ThermalPose,
        gsd: float,
        centre_ne: tuple[float, float],
        reach_m: float,
        temp_c: float,
        inside: Callable[[Any, Any], Any],
    ) -> None:
        """Blend an object at ``temp_c`` into ``frame`` by the fraction of each pixel it
        covers (5x5 samples a pixel). ``inside(dn, de)`` says which offsets (metres
        north/east of ``centre_ne``) belong to it; ``reach_m`` bounds it."""
        assert self._origin is not None and pose.lat is not None and pose.lon is not None
        n0, e0 = local_offset_m(self._origin, (pose.lat, pose.lon))
        h, w = frame.shape
        right, fwd = _ne_to_camera(centre_ne[0] - n0, centre_ne[1] - e0, pose.heading_deg)
        col, row = right / gsd + w / 2, h / 2 - fwd / gsd
        span = reach_m / gsd + 1
        r0, r1 = max(0, int(row - span)), min(h, int(row + span) + 1)
        c0, c1 = max(0, int(col - span)), min(w, int(col + span) + 1)
        if r0 >= r1 or c0 >= c1:
            return  # outside the footprint
        sub = (np.arange(_SUBSAMPLES) + 0.5) / _SUBSAMPLES
        rr = (np.arange(r0, r1)[:, None] + sub[None, :]).ravel()  # sample rows
        cc = (np.arange(c0, c1)[:, None] + sub[None, :]).ravel()
        s_right = (cc - w / 2) * gsd
        s_fwd = (h / 2 - rr) * gsd
        dn, de = _camera_to_ne(s_right[None, :], s_fwd[:, None], pose.heading_deg)
        dn, de = dn + n0 - centre_ne[0], de + e0 - centre_ne[1]
        hit = inside(dn, de).astype(np.float32)
        cover = hit.reshape(r1 - r0, _SUBSAMPLES, c1 - c0, _SUBSAMPLES).mean(axis=(1, 3))
        patch = frame[r0:r1, c0:c1]
        patch += cover * (np.float32(temp_c) - patch)


#: Separable 3-tap point spread: a small lens blurs a point ~30 % into its neighbours.
_PSF: Final = (0.15, 0.7, 0.15)


def _blur(img: Celsius) -> Celsius:
    a, b, _ = _PSF
    padded = np.pad(img, 1, mode="edge")
    rows = b * padded[1:-1] + a * (padded[:-2] + padded[2:])
    out: Celsius = (b * rows[:, 1:-1] + a * (rows[:, :-2] + rows[:, 2:])).astype(np.float32)
    return out


def _ellipse_inside(yaw_deg: float) -> Callable[[Any, Any], Any]:
    a, b = _SHOULDERS_M
    psi = math.radians(yaw_deg)
    c, s = math.cos(psi), math.sin(psi)

    def inside(dn: Any, de: Any) -> Any:
        across, along = -dn * s + de * c, dn * c + de * s
        return (across / a) ** 2 + (along / b) ** 2 <= 1.0

    return inside


def _disc_inside() -> Callable[[Any, Any], Any]:
    def inside(dn: Any, de: Any) -> Any:
        return dn * dn + de * de <= _HEAD_RADIUS_M**2

    return inside


def _box_inside(half: tuple[float, float]) -> Callable[[Any, Any], Any]:
    def inside(dn: Any, de: Any) -> Any:
        return (np.abs(dn) <= half[0]) & (np.abs(de) <= half[1])

    return inside


def y16_to_celsius(raw: npt.NDArray[np.uint16], kelvin_per_count: float = 0.01) -> Celsius:
    """Radiometric Y16 counts to degrees Celsius: ``raw * kelvin_per_count - 273.15``.

    A Lepton 3.5 in TLinear mode (PureThermal's default UVC Y16 stream) sends
    centikelvin (``kelvin_per_count`` 0.01; 0.1 in its low-resolution TLinear mode):
    29 515 is 22.0 degC.
    """
    return (raw.astype(np.float32) * np.float32(kelvin_per_count)) - np.float32(KELVIN_OFFSET)


class V4L2Thermal:
    """A UVC thermal camera sending Y16 on Linux (FLIR Lepton 3.5 on a PureThermal 1/2/
    Mini board: ``/dev/video0``, 160x120, ~9 fps), read with PyAV's v4l2 demuxer.

    FFmpeg's v4l2 input maps ``input_format="gray16le"`` to V4L2_PIX_FMT_Y16. The
    device is opened on the first capture (in a worker thread: V4L2 negotiation
    blocks), each frame is read in a worker thread, and the pose is sampled when the
    frame arrives (the Lepton's own latency, about one frame, is not compensated).
    Raises ThermalError when the device cannot be opened or sends counts that are not
    radiometric (TLinear off: values far below 0 degC). Not exercised by the test
    suite (no device); see docs/rescue-agent.md.
    """

    def __init__(
        self,
        pose: PoseFn,
        *,
        device: str = "/dev/video0",
        width: int = DEFAULT_WIDTH,
        height: int = DEFAULT_HEIGHT,
        hfov_deg: float = DEFAULT_HFOV_DEG,
        fps: float = DEFAULT_FPS,
        input_format: str = "gray16le",
        kelvin_per_count: float = 0.01,
        alt_offset_m: float = 0.0,
    ) -> None:
        _check_geometry(width, height, hfov_deg, fps)
        self.width, self.height, self.hfov_deg, self.fps = width, height, hfov_deg, fps
        self.device = device
        self.kelvin_per_count = kelvin_per_count
        self.alt_offset_m = alt_offset_m
        self.options = {
            "input_format": input_format,
            "video_size": f"{width}x{height}",
            "framerate": f"{fps:g}",
        }
        self._pose = pose
        self._container: Any = None
        self._frames: Any = None

    def _open(self) -> None:
        import av  # only thermal agents with a real camera load FFmpeg for this

        try:
            self._container = av.open(self.device, format="v4l2", options=dict(self.options))
        except (OSError, av.FFmpegError) as exc:
            raise ThermalError(f"cannot open thermal camera {self.device}: {exc}") from exc
        self._frames = self._container.decode(video=0)

    def _read(self) -> npt.NDArray[np.uint16]:
        if self._container is None:
            self._open()
        try:
            frame = next(self._frames)
        except StopIteration:
            raise ThermalError(f"{self.device}: the stream ended") from None
        raw: npt.NDArray[np.uint16] = frame.to_ndarray(format="gray16le")
        return raw

    async def capture(self) -> tuple[Celsius, ThermalPose]:
        try:
            raw = await asyncio.to_thread(self._read)
        except ThermalError:
            await self.close()
            raise
        except Exception as exc:  # FFmpeg read errors: report, reopen on the next call
            await self.close()
            raise ThermalError(f"{self.device}: {exc}") from exc
        pose = ThermalPose.coerce(self._pose(), alt_offset_m=self.alt_offset_m)
        frame = y16_to_celsius(raw, self.kelvin_per_count)
        if float(np.median(frame)) < -100.0:
            raise ThermalError(
                f"{self.device} sends raw counts, not temperatures: enable radiometry "
                "(TLinear) on the Lepton, or set kelvin_per_count"
            )
        return frame, pose

    async def close(self) -> None:
        container, self._container, self._frames = self._container, None, None
        if container is not None:
            with contextlib.suppress(Exception):
                await asyncio.to_thread(container.close)


def _check_geometry(width: int, height: int, hfov_deg: float, fps: float) -> None:
    if not (8 <= width <= 4096 and 8 <= height <= 4096):
        raise ValueError("thermal width and height must be 8..4096 pixels")
    if not 1.0 <= hfov_deg <= 170.0:
        raise ValueError("thermal hfov_deg must be in [1, 170]")
    if not 0 < fps <= 60:
        raise ValueError("thermal fps must be in (0, 60]")


# --------------------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------------------

_COMMON_KEYS: Final = {"source", "width", "height", "hfov_deg", "fps", "alt_offset_m", "detection"}
_SOURCE_KEYS: Final = {
    "synthetic": {
        "persons",
        "boats",
        "glints",
        "sea_c",
        "person_c",
        "boat_c",
        "ground_c",
        "noise_c",
        "wave_c",
        "seed",
    },
    "v4l2": {"device", "input_format", "kelvin_per_count"},
}


def _number(config: Mapping[str, Any], key: str, *, integer: bool = False) -> float | int | None:
    value = config.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"thermal {key}: must be a number")
    if integer:
        if int(value) != value:
            raise ValueError(f"thermal {key}: must be an integer")
        return int(value)
    return float(value)


def _source_options(config: Mapping[str, Any]) -> tuple[str, dict[str, Any]]:
    """Validate a thermal config; (source kind, keyword arguments of its class)."""
    if not isinstance(config, Mapping):
        raise ValueError("thermal: must be an object")
    kind = config.get("source")
    if kind not in _SOURCE_KEYS:
        raise ValueError(f"thermal source: must be one of {', '.join(sorted(_SOURCE_KEYS))}")
    unknown = set(config) - _COMMON_KEYS - _SOURCE_KEYS[kind]
    if unknown:
        raise ValueError(f"thermal ({kind}): unknown key(s) {', '.join(sorted(unknown))}")
    options: dict[str, Any] = {}
    for key in ("width", "height", "seed"):
        value = _number(config, key, integer=True)
        if value is not None:
            options[key] = value
    for key in ("hfov_deg", "fps", "alt_offset_m", "kelvin_per_count"):
        value = _number(config, key)
        if value is not None:
            options[key] = value
    for key in ("sea_c", "person_c", "boat_c", "ground_c", "noise_c", "wave_c"):
        value = _number(config, key)
        if value is not None:
            if not -50 <= value <= 150:
                raise ValueError(f"thermal {key}: must be a temperature in -50..150 degC")
            options[key] = value
    for key in ("noise_c", "wave_c"):
        if options.get(key, 0) < 0:
            raise ValueError(f"thermal {key}: must not be negative")
    if "kelvin_per_count" in options and options["kelvin_per_count"] <= 0:
        raise ValueError("thermal kelvin_per_count: must be positive")
    for key, extra in (("persons", 0), ("boats", 2), ("glints", 2)):
        if key in config:
            options[key] = _latlon_list(config[key], key, extra)
    for key in ("device", "input_format"):
        if key in config:
            if not isinstance(config[key], str) or not config[key]:
                raise ValueError(f"thermal {key}: must be a non-empty string")
            options[key] = config[key]
    _check_geometry(
        options.get("width", DEFAULT_WIDTH),
        options.get("height", DEFAULT_HEIGHT),
        options.get("hfov_deg", DEFAULT_HFOV_DEG),
        options.get("fps", DEFAULT_FPS),
    )
    return kind, options


def thermal_config_check(config: Mapping[str, Any]) -> None:
    """Validate the agent's ``thermal`` section without opening anything; ValueError
    names the bad key."""
    _source_options(config)
    detection = config.get("detection", {})
    if not isinstance(detection, Mapping):
        raise ValueError("thermal detection: must be an object")
    DetectorSettings.from_mapping(detection)


def thermal_source_create(config: Mapping[str, Any], pose: PoseFn) -> ThermalSource:
    """The source the agent's ``thermal`` section describes.

    ``{"source": "synthetic", "persons": [[lat, lon], ...], "sea_c": 16, "person_c":
    34, "seed": 1, ...}`` or ``{"source": "v4l2", "device": "/dev/video0"}``; common
    keys ``width``, ``height``, ``hfov_deg``, ``fps``, ``alt_offset_m`` (take-off
    point's height above the water) and ``detection`` (see :class:`DetectorSettings`,
    used by :func:`thermal_feed_create`). ``pose`` returns the vehicle's pose (a
    mapping or a VehicleState). Raises ValueError naming a bad or unknown key; nothing
    is opened until the first capture.
    """
    kind, options = _source_options(config)
    if kind == "synthetic":
        return SyntheticSeaThermal(pose, **options)
    return V4L2Thermal(pose, **options)


def thermal_feed_create(config: Mapping[str, Any], pose: PoseFn) -> ThermalFeed:
    """The agent's :class:`ThermalFeed`: :func:`thermal_source_create` plus the
    ``detection`` settings. Raises ValueError on a bad configuration."""
    thermal_config_check(config)
    settings = DetectorSettings.from_mapping(config.get("detection", {}))
    return ThermalFeed(thermal_source_create(config, pose), settings=settings)


# --------------------------------------------------------------------------------------
# The shared feed
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ThermalFrame:
    """One analysed frame: ``seq`` counts frames of the feed from 1, ``t`` is the Unix
    time of capture, ``gsd_m`` None when too low to see anything, ``blobs`` what
    :func:`detect_persons` found (empty without a GSD), ``detect_ms`` its run time."""

    seq: int
    t: float
    celsius: Celsius
    pose: ThermalPose
    gsd_m: float | None
    blobs: tuple[Blob, ...]
    detect_ms: float


class ThermalFeed:
    """The agent's one thermal camera, shared by the mission runner and the video.

    ``await frame(newer_than=seq)`` returns the latest frame if it is newer than
    ``seq``, else waits for the next: a capture is started on demand, and callers that
    arrive while one is under way share it. So every frame is captured and analysed
    (detection, in a worker thread) once however many readers there are, and nothing
    is captured while nobody reads. Use as ``async with``: leaving closes the source.
    """

    def __init__(
        self, source: ThermalSource, *, settings: DetectorSettings = DEFAULT_DETECTOR
    ) -> None:
        self.source = source
        self.settings = settings
        self.latest: ThermalFrame | None = None
        self._pending: asyncio.Future[ThermalFrame] | None = None
        self._seq = 0

    @property
    def width(self) -> int:
        return self.source.width

    @property
    def height(self) -> int:
        return self.source.height

    @property
    def hfov_deg(self) -> float:
        return self.source.hfov_deg

    @property
    def fps(self) -> float:
        return self.source.fps

    async def frame(self, newer_than: int = 0) -> ThermalFrame:
        """A frame with ``seq > newer_than``. Raises ThermalError when the camera fails
        (the next call tries again)."""
        latest = self.latest
        if latest is not None and latest.seq > newer_than:
            return latest
        if self._pending is None or self._pending.done():
            self._pending = asyncio.ensure_future(self._capture())
            # A failure nobody is left to await must not be logged as "never retrieved".
            self._pending.add_done_callback(lambda f: f.cancelled() or f.exception())
        # Shielded: one reader giving up (cancelled) must not cancel the others' frame.
        return await asyncio.shield(self._pending)

    async def _capture(self) -> ThermalFrame:
        celsius, pose = await self.source.capture()
        gsd = ground_sample_distance_m(pose.alt, self.hfov_deg, self.width)
        blobs: list[Blob] = []
        started = time.perf_counter()
        if gsd is not None:
            blobs = await asyncio.to_thread(
                detect_persons, celsius, gsd_m=gsd, settings=self.settings
            )
        self._seq += 1
        frame = ThermalFrame(
            seq=self._seq,
            t=time.time(),
            celsius=celsius,
            pose=pose,
            gsd_m=gsd,
            blobs=tuple(blobs),
            detect_ms=(time.perf_counter() - started) * 1000.0,
        )
        self.latest = frame
        return frame

    async def close(self) -> None:
        """Stop a capture under way and close the source."""
        pending, self._pending = self._pending, None
        if pending is not None and not pending.done():
            pending.cancel()
            with contextlib.suppress(asyncio.CancelledError, ThermalError):
                await pending
        await self.source.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()


# --------------------------------------------------------------------------------------
# False colour
# --------------------------------------------------------------------------------------

# Ironbow: black, indigo, purple, red, orange, yellow, white.
_IRONBOW_STOPS: Final = (
    (0.00, (0, 0, 0)),
    (0.10, (20, 0, 90)),
    (0.30, (120, 0, 150)),
    (0.50, (200, 30, 100)),
    (0.65, (240, 90, 20)),
    (0.80, (255, 170, 0)),
    (0.92, (255, 230, 80)),
    (1.00, (255, 255, 255)),
)


def _ironbow() -> RGB:
    x = np.linspace(0.0, 1.0, 256)
    at = [s[0] for s in _IRONBOW_STOPS]
    channels = [np.interp(x, at, [s[1][k] for s in _IRONBOW_STOPS]) for k in range(3)]
    return np.stack(channels, axis=1).round().astype(np.uint8)


IRONBOW: Final = _ironbow()


def _resize_bilinear(
    img: npt.NDArray[np.float32], out_h: int, out_w: int
) -> npt.NDArray[np.float32]:
    h, w = img.shape

    def axis(n_out: int, n_in: int) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.float32]]:
        pos = np.clip((np.arange(n_out, dtype=np.float32) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
        i0 = np.minimum(pos.astype(np.intp), n_in - 2) if n_in > 1 else np.zeros(n_out, np.intp)
        return i0, (pos - i0).astype(np.float32)

    r0, fr = axis(out_h, h)
    c0, fc = axis(out_w, w)
    r1 = np.minimum(r0 + 1, h - 1)
    c1 = np.minimum(c0 + 1, w - 1)
    rows = img[r0] * (1 - fr)[:, None] + img[r1] * fr[:, None]
    out: Celsius = rows[:, c0] * (1 - fc)[None, :] + rows[:, c1] * fc[None, :]
    return out


def colour_range(frame_c: Celsius) -> tuple[float, float]:
    """(low, high) temperatures mapped to the ends of the palette: from just under the
    coldest percent of the frame to its warmest pixel, at least 8 degC wide so that
    open water shows its texture without the noise filling the palette."""
    low = float(np.percentile(frame_c, 1)) - 0.5
    return low, max(float(np.max(frame_c)), low + 8.0)


def false_colour(
    frame_c: Celsius,
    blobs: Sequence[Blob] = (),
    *,
    width: int = 640,
    height: int = 480,
    box_confidence: float = 0.6,
) -> RGB:
    """An H x W x 3 RGB picture of a thermal frame: ironbow palette over
    :func:`colour_range`, upscaled bilinearly to ``width`` x ``height``, and a box round
    each blob (green at ``box_confidence`` or more, yellow below)."""
    low, high = colour_range(frame_c)
    scaled = (np.asarray(frame_c, dtype=np.float32) - low) * np.float32(255.0 / (high - low))
    big = _resize_bilinear(scaled, height, width)
    img: RGB = IRONBOW[np.clip(big, 0, 255).astype(np.uint8)]
    sy, sx = height / frame_c.shape[0], width / frame_c.shape[1]
    for blob in blobs:
        r0, c0, r1, c1 = blob.box
        pad = 3
        y0, y1 = max(0, int(r0 * sy) - pad), min(height, int(r1 * sy) + pad)
        x0, x1 = max(0, int(c0 * sx) - pad), min(width, int(c1 * sx) + pad)
        colour = (0, 255, 0) if blob.confidence >= box_confidence else (255, 220, 0)
        t = 2
        img[y0 : y0 + t, x0:x1] = colour
        img[max(y0, y1 - t) : y1, x0:x1] = colour
        img[y0:y1, x0 : x0 + t] = colour
        img[y0:y1, max(x0, x1 - t) : x1] = colour
    return img
