"""Reading back the geotags the agent's photographer writes (agents.stills), for the
tests that check where a photo says it was taken."""

from __future__ import annotations

import io


def photo_position(jpeg: bytes) -> tuple[float, float] | None:
    """The (lat, lon) a JPEG's EXIF GPS tags give, or None."""
    from PIL import ExifTags, Image

    gps = Image.open(io.BytesIO(jpeg)).getexif().get_ifd(ExifTags.IFD.GPSInfo)
    try:
        lat = sum(float(x) / 60**i for i, x in enumerate(gps[ExifTags.GPS.GPSLatitude]))
        lon = sum(float(x) / 60**i for i, x in enumerate(gps[ExifTags.GPS.GPSLongitude]))
    except (KeyError, TypeError, ValueError):
        return None
    if gps.get(ExifTags.GPS.GPSLatitudeRef) == "S":
        lat = -lat
    if gps.get(ExifTags.GPS.GPSLongitudeRef) == "W":
        lon = -lon
    return lat, lon
