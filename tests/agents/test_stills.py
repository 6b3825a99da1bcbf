"""The camera missions photograph with (agents.stills): the simulated nadir camera sees
a ground that is a fixed function of latitude and longitude, from wherever and whichever
way it looks; its JPEG carries where it was taken in EXIF GPS tags; the agent's ``photo``
section is checked naming the key."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from PIL import Image

from agents.config import AgentConfig, ConfigError
from agents.geo import offset
from agents.protocol import generate_keypair
from agents.stills import (
    NadirSimCamera,
    ground_rgb,
    nadir_lat_lon,
    still_camera_create,
)
from tests.agents.geotags import photo_position

HOME = (40.6306, -8.6588)


def test_the_ground_is_the_same_wherever_it_is_seen_from() -> None:
    camera = NadirSimCamera(hfov_deg=60, width=200, height=150, quality=90)
    here = {"lat": HOME[0], "lon": HOME[1], "alt": 40.0, "heading_deg": 0.0}
    picture = camera.render(here)
    assert picture.shape == (150, 200, 3)
    # Each pixel is the ground where nadir_lat_lon puts it.
    lat, lon = nadir_lat_lon(here, hfov_deg=60, width=200, height=150)
    assert np.array_equal(picture, ground_rgb(lat, lon))
    # 40 m up with 60° across: 46.2 m of ground over 200 px; north is the top.
    assert lat[0, 100] > lat[-1, 100] and lon[75, -1] > lon[75, 0]
    width_m = (
        (lon[75, -1] - lon[75, 0]) * math.pi / 180 * 6_371_008.8 * math.cos(math.radians(HOME[0]))
    )
    assert width_m == pytest.approx(2 * 40 * math.tan(math.radians(30)) * 199 / 200, rel=1e-3)
    # Seen from 10 m further east, every pixel's ground is 10 m further east: the
    # same ground, whatever the vehicle's position.
    moved = offset(HOME, 0, 10)
    lat2, lon2 = nadir_lat_lon(
        {**here, "lat": moved[0], "lon": moved[1]}, hfov_deg=60, width=200, height=150
    )
    assert np.allclose(lat2, lat) and np.allclose(lon2 - lon, moved[1] - HOME[1], atol=1e-9)
    # Flying east (heading 90°), the picture's top is east and its left north.
    east = {**here, "heading_deg": 90.0}
    lat_e, lon_e = nadir_lat_lon(east, hfov_deg=60, width=200, height=150)
    assert lon_e[0, 100] > lon_e[-1, 100] and lat_e[75, 0] > lat_e[75, -1]


def test_the_ground_has_fields_hedges_and_tracks() -> None:
    north = np.linspace(0, 400, 800)
    lat, lon = offset(HOME, 0, 0)
    lats = lat + np.degrees(north / 6_371_008.8)
    colours = ground_rgb(lats, np.full_like(lats, lon))
    assert len({tuple(c) for c in colours}) > 10  # not a flat colour
    assert np.array_equal(colours, ground_rgb(lats, np.full_like(lats, lon)))  # fixed


async def test_a_photo_is_a_jpeg_tagged_with_where_it_was_taken() -> None:
    camera = still_camera_create(
        {"source": "nadir", "hfov_deg": 73.7, "width": 320, "height": 240, "quality": 80}
    )
    async with camera:
        photo = await camera.capture(
            {"lat": HOME[0], "lon": HOME[1], "alt": 30.0, "heading_deg": 45.0}
        )
    image = Image.open(io.BytesIO(photo.jpeg))
    assert image.format == "JPEG" and image.size == (320, 240)
    lat, lon = photo_position(photo.jpeg) or (0, 0)
    assert lat == pytest.approx(HOME[0], abs=1e-6) and lon == pytest.approx(HOME[1], abs=1e-6)
    assert photo.meta["heading_deg"] == 45.0 and photo.meta["alt"] == 30.0
    assert (photo.meta["width"], photo.meta["height"], photo.meta["hfov_deg"]) == (320, 240, 73.7)
    with pytest.raises(OSError, match="no position"):
        await camera.capture({"lat": None, "lon": None})


BASE = {
    "platform_url": "wss://iouv.example.org",
    "vehicle_id": "v-1",
    "credential": "secret",
    "platform_public_key": generate_keypair()[1],
    "adapter": "car",
}


@pytest.mark.parametrize(
    ("photo", "named"),
    [
        ({"source": "fisheye", "hfov_deg": 60, "width": 64, "height": 48}, "photo.source"),
        ({"source": "nadir", "hfov_deg": 0, "width": 64, "height": 48}, "photo.hfov_deg"),
        ({"source": "nadir", "hfov_deg": 60, "width": 6.5, "height": 48}, "photo.width"),
        ({"source": "nadir", "hfov_deg": 60, "width": 64, "height": 48, "zoom": 2}, "photo.zoom"),
        ({"source": "v4l2", "hfov_deg": 60, "width": 64, "height": 48}, "photo.device"),
        (
            {"source": "nadir", "hfov_deg": 60, "width": 64, "height": 48, "quality": 100},
            "photo.quality",
        ),
    ],
)
def test_a_bad_photo_section_is_refused_naming_the_key(photo, named) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        AgentConfig.from_mapping({**BASE, "photo": photo})


def test_a_good_photo_section_says_which_camera_missions_photograph_with() -> None:
    photo = {
        "source": "v4l2",
        "device": "/dev/video2",
        "hfov_deg": 70,
        "width": 1920,
        "height": 1080,
    }
    assert AgentConfig.from_mapping({**BASE, "photo": photo}).photo == photo
    assert AgentConfig.from_mapping(BASE).photo is None
