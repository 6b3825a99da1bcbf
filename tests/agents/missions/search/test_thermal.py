"""agents.missions.search.thermal: the synthetic sea, person detection, geolocation,
the shared feed and its false-colour video. Pure numpy frames; no camera, no vehicle."""

from __future__ import annotations

import asyncio
import math
import random
import time
from typing import Any

import numpy as np
import pytest

from agents.config import AgentConfig, ConfigError
from agents.geo import distance_m, offset
from agents.missions.registry import mission
from agents.missions.search.thermal import (
    DetectorSettings,
    SyntheticSeaThermal,
    ThermalFeed,
    ThermalPose,
    V4L2Thermal,
    detect_persons,
    footprint_m,
    geolocate,
    ground_sample_distance_m,
    thermal_config_check,
    thermal_feed_create,
    thermal_source_create,
    y16_to_celsius,
)
from agents.missions.search.video import ThermalVideo
from agents.protocol import generate_keypair
from agents.video import VideoError
from agents.video.sources import video_source_create

SEA = (40.6406, -8.6788)
W, H, HFOV = 160, 120, 57.0


def gsd(alt: float) -> float:
    value = ground_sample_distance_m(alt, HFOV, W)
    assert value is not None
    return value


def pose_seeing(
    target: tuple[float, float], alt: float, heading: float, rng: random.Random
) -> ThermalPose:
    """A pose at ``alt`` and ``heading`` whose footprint has ``target`` somewhere in its
    inner 80 %."""
    across, along = footprint_m(alt, HFOV, W, H)
    right = rng.uniform(-0.4, 0.4) * across
    forward = rng.uniform(-0.4, 0.4) * along
    psi = math.radians(heading)
    north = forward * math.cos(psi) - right * math.sin(psi)
    east = forward * math.sin(psi) + right * math.cos(psi)
    lat, lon = offset(target, -north, -east)
    return ThermalPose(lat, lon, alt, heading)


def no_pose() -> dict[str, Any]:
    return {}


# --- detection and geolocation ---------------------------------------------------------


@pytest.mark.parametrize("alt", [30.0, 40.0, 50.0, 60.0])
def test_person_is_found_and_geolocated_within_a_metre(alt: float) -> None:
    rng = random.Random(int(alt))
    errors: list[float] = []
    for trial in range(24):
        heading = trial * 15.0  # all round the compass
        person = offset(SEA, rng.uniform(-300, 300), rng.uniform(-300, 300))
        pose = pose_seeing(person, alt, heading, rng)
        sea = SyntheticSeaThermal(no_pose, persons=[person], seed=trial)
        frame = sea.render(pose, t=trial * 0.37)
        # How long detection takes is not asserted (a loaded machine): each frame reports
        # it (ThermalFrame.detect_ms).
        blobs = detect_persons(frame, gsd_m=gsd(alt))
        assert len(blobs) == 1, (alt, heading, blobs)
        blob = blobs[0]
        assert blob.confidence >= 0.6
        assert 0.1 <= blob.area_m2 <= 0.4  # head and shoulders
        assert 20.0 <= blob.peak_c <= 34.5  # mixed into the water at high altitude
        errors.append(distance_m(geolocate(blob, pose, HFOV, W, H), person))
    assert max(errors) < 1.0, errors


def test_two_persons_are_two_blobs() -> None:
    a, b = offset(SEA, 3, 0), offset(SEA, -4, 6)
    pose = ThermalPose(SEA[0], SEA[1], 40.0, 0.0)
    frame = SyntheticSeaThermal(no_pose, persons=[a, b], seed=4).render(pose)
    blobs = detect_persons(frame, gsd_m=gsd(40))
    found = sorted(distance_m(geolocate(blob, pose, HFOV, W, H), a) for blob in blobs)
    assert len(blobs) == 2 and found[0] < 1.0 and 8 < found[1] < 10


def test_empty_sea_has_no_false_positives() -> None:
    rng = random.Random(7)
    for seed in range(400):
        alt = rng.uniform(20, 80)
        pose = ThermalPose(SEA[0], SEA[1], alt, rng.uniform(0, 360))
        sea = SyntheticSeaThermal(no_pose, seed=seed, sea_c=rng.uniform(8, 24))
        frame = sea.render(pose, t=seed * 0.5)
        assert detect_persons(frame, gsd_m=gsd(alt)) == [], seed


def test_rough_water_and_a_noisy_sensor_are_not_persons() -> None:
    for seed in range(50):
        sea = SyntheticSeaThermal(no_pose, seed=seed, wave_c=1.5, noise_c=0.6)
        frame = sea.render(ThermalPose(SEA[0], SEA[1], 40.0, 10.0 * seed))
        assert detect_persons(frame, gsd_m=gsd(40)) == [], seed


@pytest.mark.parametrize("alt", [30.0, 45.0, 60.0])
@pytest.mark.parametrize(("radius_m", "delta_c"), [(4, 4), (6, 6), (10, 8), (3, 10)])
def test_sun_glint_is_not_a_person(alt: float, radius_m: float, delta_c: float) -> None:
    glint = [*offset(SEA, 2, -3), radius_m, delta_c]
    frame = SyntheticSeaThermal(no_pose, glints=[glint], seed=3).render(
        ThermalPose(SEA[0], SEA[1], alt, 30.0)
    )
    assert frame.max() > 16 + delta_c * 0.8  # it is there, and warm
    assert detect_persons(frame, gsd_m=gsd(alt)) == []


@pytest.mark.parametrize("alt", [30.0, 45.0, 60.0])
@pytest.mark.parametrize(("length_m", "width_m"), [(2.5, 1.2), (5, 2), (8, 3)])
def test_boat_is_not_a_person(alt: float, length_m: float, width_m: float) -> None:
    boat = [*offset(SEA, -3, 4), length_m, width_m]
    frame = SyntheticSeaThermal(no_pose, boats=[boat], seed=5).render(
        ThermalPose(SEA[0], SEA[1], alt, 75.0)
    )
    assert detect_persons(frame, gsd_m=gsd(alt)) == []


def test_person_beside_a_boat_and_a_glint_is_still_found() -> None:
    person = offset(SEA, 0, 0)
    sea = SyntheticSeaThermal(
        no_pose,
        persons=[person],
        boats=[[*offset(SEA, 0, 6), 5, 2]],
        glints=[[*offset(SEA, -6, -4), 6, 5]],
        seed=9,
    )
    pose = ThermalPose(*offset(SEA, 3, 3), 40.0, 200.0)
    blobs = detect_persons(sea.render(pose), gsd_m=gsd(40))
    assert len(blobs) == 1
    assert distance_m(geolocate(blobs[0], pose, HFOV, W, H), person) < 1.0


def test_hot_objects_and_hot_pixels_are_rejected() -> None:
    pose = ThermalPose(SEA[0], SEA[1], 40.0, 0.0)
    frame = SyntheticSeaThermal(no_pose, seed=1).render(pose)
    frame[30, 30] = 60.0  # a dead (stuck hot) pixel: far too small
    frame[80:82, 100:102] = 55.0  # an engine: person-sized but too hot
    assert detect_persons(frame, gsd_m=gsd(40)) == []


def test_lukewarm_resolved_patch_is_too_cold_to_be_a_person() -> None:
    pose = ThermalPose(SEA[0], SEA[1], 30.0, 0.0)
    frame = SyntheticSeaThermal(no_pose, seed=1).render(pose)
    frame[50:54, 70:74] += 6.0  # 0.6 m2 at 22 degC, well resolved: foam, a glint
    assert detect_persons(frame, gsd_m=gsd(30)) == []
    frame[50:54, 70:74] += 10.0  # the same at 32 degC is a person
    assert len(detect_persons(frame, gsd_m=gsd(30))) == 1


def test_detector_settings_from_config() -> None:
    assert DetectorSettings.from_mapping({"min_contrast_c": 4}).min_contrast_c == 4.0
    with pytest.raises(ValueError, match="unknown key"):
        DetectorSettings.from_mapping({"k": 3})
    with pytest.raises(ValueError, match="min_area_m2"):
        DetectorSettings.from_mapping({"min_area_m2": 2, "max_area_m2": 1})
    with pytest.raises(ValueError, match="must be a number"):
        DetectorSettings.from_mapping({"k_sigma": "5"})


def test_geolocate_turns_image_offsets_with_the_heading() -> None:
    from agents.missions.search.thermal import Blob

    # A blob 10 pixels right of the centre at 40 m: right of the nose, whatever the
    # heading; heading east puts it south of the drone.
    blob = Blob(60.0, 90.0, 1, 0.2, 0.1, 30.0, 30.0, 16.0, 1.0, (59, 89, 61, 91))
    g = gsd(40)
    east_pose = ThermalPose(SEA[0], SEA[1], 40.0, 90.0)
    assert distance_m(geolocate(blob, east_pose, HFOV, W, H), offset(SEA, -10 * g, 0)) < 0.01
    north_pose = ThermalPose(SEA[0], SEA[1], 40.0, 0.0)
    assert distance_m(geolocate(blob, north_pose, HFOV, W, H), offset(SEA, 0, 10 * g)) < 0.01
    with pytest.raises(ValueError):
        geolocate(blob, ThermalPose(SEA[0], SEA[1], 0.5, 0.0), HFOV, W, H)
    with pytest.raises(ValueError):
        geolocate(blob, ThermalPose(None, None, 40.0, 0.0), HFOV, W, H)


def test_on_the_ground_it_sees_nothing() -> None:
    sea = SyntheticSeaThermal(no_pose, persons=[SEA])
    for alt in (None, 0.0, 0.9):
        frame = sea.render(ThermalPose(SEA[0], SEA[1], alt, 0.0))
        assert abs(float(np.median(frame)) - 20.0) < 0.1 and frame.max() < 22.5
    assert ground_sample_distance_m(0.9, HFOV, W) is None


def test_pose_accepts_mappings_and_state_objects() -> None:
    from agents.vehicles.base import VehicleState

    pose = ThermalPose.coerce({"lat": 1, "lon": 2, "alt": 30, "heading": 90}, alt_offset_m=2)
    assert pose == ThermalPose(1.0, 2.0, 32.0, 90.0)
    state = VehicleState(lat=1.0, lon=2.0, alt=None, heading_deg=45.0)
    assert ThermalPose.coerce(state) == ThermalPose(1.0, 2.0, None, 45.0)


# --- configuration and sources ---------------------------------------------------------


def test_y16_centikelvin_to_celsius() -> None:
    raw = np.array([[27315, 29515], [30715, 0]], dtype=np.uint16)
    c = y16_to_celsius(raw)
    assert c.dtype == np.float32
    assert np.allclose(c, [[0.0, 22.0], [34.0, -273.15]], atol=1e-3)
    assert np.allclose(y16_to_celsius(np.array([3075], dtype=np.uint16), 0.1), [34.35], atol=1e-3)


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({}, "source"),
        ({"source": "flir"}, "source"),
        ({"source": "synthetic", "persons": [[1, 2, 3]]}, r"persons\[0\]"),
        ({"source": "synthetic", "persons": [[91, 0]]}, "out of range"),
        ({"source": "synthetic", "persons": "here"}, "must be a list"),
        ({"source": "synthetic", "boats": [[1, 2, 3, -1]]}, "positive"),
        ({"source": "synthetic", "sea_c": "cold"}, "sea_c"),
        ({"source": "synthetic", "sea_c": 400}, "sea_c"),
        ({"source": "synthetic", "noise_c": -1}, "noise_c"),
        ({"source": "synthetic", "seed": 1.5}, "seed"),
        ({"source": "synthetic", "device": "/dev/video0"}, "unknown key"),
        ({"source": "v4l2", "persons": []}, "unknown key"),
        ({"source": "v4l2", "device": ""}, "device"),
        ({"source": "v4l2", "kelvin_per_count": 0}, "kelvin_per_count"),
        ({"source": "v4l2", "fps": 0}, "fps"),
        ({"source": "v4l2", "hfov_deg": 200}, "hfov_deg"),
        ({"source": "v4l2", "width": 4}, "width"),
        ({"source": "v4l2", "width": True}, "width"),
        ({"source": "v4l2", "detection": {"nope": 1}}, "unknown key"),
        ({"source": "v4l2", "detection": []}, "detection"),
    ],
)
def test_bad_config_raises_value_error_naming_the_key(config: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        thermal_config_check(config)
    if "detection" not in config:
        with pytest.raises(ValueError, match=message):
            thermal_source_create(config, no_pose)


def test_source_create_dispatches() -> None:
    synthetic = thermal_source_create(
        {"source": "synthetic", "persons": [list(SEA)], "hfov_deg": 50, "fps": 5}, no_pose
    )
    assert isinstance(synthetic, SyntheticSeaThermal)
    assert (synthetic.hfov_deg, synthetic.fps, synthetic.persons) == (50.0, 5.0, [SEA])
    camera = thermal_source_create({"source": "v4l2", "device": "/dev/video9"}, no_pose)
    assert isinstance(camera, V4L2Thermal)
    assert camera.options == {"input_format": "gray16le", "video_size": "160x120", "framerate": "9"}


async def test_v4l2_without_a_device_raises_thermal_error() -> None:
    from agents.missions.search.thermal import ThermalError

    camera = V4L2Thermal(no_pose, device="/dev/nonexistent-thermal")
    with pytest.raises(ThermalError, match="cannot open"):
        await camera.capture()
    await camera.close()


def test_agent_config_thermal_section() -> None:
    base = {
        "platform_url": "ws://127.0.0.1:1",
        "vehicle_id": "v",
        "credential": "c",
        # The config loads the key, so it must be a real one.
        "platform_public_key": generate_keypair()[1],
        "adapter": "mavlink",
    }
    config = AgentConfig.from_mapping(
        {**base, "thermal": {"source": "synthetic"}, "video": {"source": "thermal"}}
    )
    assert config.sensors == {"thermal": {"source": "synthetic"}}
    with pytest.raises(ConfigError, match="thermal"):
        AgentConfig.from_mapping({**base, "thermal": {"source": "synthetic", "bad": 1}})
    with pytest.raises(ConfigError, match="thermal section"):
        AgentConfig.from_mapping({**base, "video": {"source": "thermal"}})


# --- the shared feed and its video -----------------------------------------------------


async def test_feed_shares_each_frame_between_readers() -> None:
    person = offset(SEA, 4, -2)
    pose = {"lat": SEA[0], "lon": SEA[1], "alt": 40.0, "heading_deg": 0.0}
    feed = thermal_feed_create(
        {"source": "synthetic", "persons": [list(person)], "fps": 20}, lambda: pose
    )
    async with feed:
        a, b = await asyncio.gather(feed.frame(), feed.frame())
        assert a is b and a.seq == 1  # one capture for both readers
        assert len(a.blobs) == 1 and a.gsd_m == pytest.approx(gsd(40))
        assert await feed.frame(newer_than=0) is a  # the latest is still new to them
        started = time.monotonic()
        c = await feed.frame(newer_than=a.seq)
        assert c.seq == 2 and time.monotonic() - started < 0.5  # paced at 20 fps
        assert distance_m(geolocate(c.blobs[0], c.pose, HFOV, W, H), person) < 1.0


async def test_feed_on_the_ground_detects_nothing() -> None:
    feed = ThermalFeed(SyntheticSeaThermal(lambda: {"lat": SEA[0], "lon": SEA[1], "alt": 0.0}))
    async with feed:
        frame = await feed.frame()
        assert frame.gsd_m is None and frame.blobs == ()


async def test_thermal_video_draws_the_detection_box() -> None:
    person = offset(SEA, 0, 0)
    pose = {"lat": SEA[0], "lon": SEA[1], "alt": 40.0, "heading_deg": 0.0}
    feed = thermal_feed_create({"source": "synthetic", "persons": [list(person)]}, lambda: pose)
    async with feed:
        # The search mission's sensor offers its video as the agent's runtime hands it.
        video = mission("search").sensor
        assert video is not None and video.video is not None
        sources = {"thermal": lambda options: video.video(feed, options)}
        source = video_source_create({"source": "thermal"}, sources=sources)
        assert isinstance(source, ThermalVideo)
        frame = await source.frame()
        assert (frame.width, frame.height) == (640, 480)
        img = frame.to_ndarray(format="rgb24")
        # The person is at the image centre: white-hot inside a green box.
        centre = img[236:244, 316:324].astype(int)
        assert centre.sum(axis=2).max() > 600
        green = (img[:, :, 1] > 200) & (img[:, :, 0] < 80) & (img[:, :, 2] < 80)
        rows, cols = np.nonzero(green[200:280, 280:360])
        assert rows.size > 20  # a box round the centre
        assert rows.min() < 40 < rows.max() and cols.min() < 40 < cols.max()
        # Water is dark in the palette.
        assert img[20:60, 20:60].astype(int).sum(axis=2).mean() < 250
        second = await source.frame()
        assert feed.latest is not None and feed.latest.seq == 2 and second is not frame
        await source.close()
    with pytest.raises(VideoError, match="thermal"):
        video_source_create({"source": "thermal"})
    with pytest.raises(VideoError, match="unknown option"):
        video_source_create({"source": "thermal", "palette": "rainbow"}, sources=sources)
