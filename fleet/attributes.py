"""Declared vehicle attributes: names, units and validation.

Every vehicle declares these values (the paper's "main attributes of each vehicle
type"); services put constraints on them. Adding an attribute means adding one entry
to ``ATTRIBUTES``: forms, the admin, validation and matching pick it up.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from django.core.exceptions import ValidationError
from django.utils.deconstruct import deconstructible

CAMERAS = ("rgb", "thermal", "lidar", "night")  # "none" is the empty list
ENVIRONMENTS = ("land", "sea", "air")


@dataclass(frozen=True)
class NumberAttribute:
    """A non-negative quantity with a unit."""

    name: str
    unit: str
    label: str
    required: bool = True
    maximum: float | None = None

    def clean(self, value: Any) -> float:
        # bool is an int in Python; "true" is not a range.
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValidationError(f"{self.name}: must be a number of {self.unit}, got {value!r}")
        if not math.isfinite(value) or value < 0:
            raise ValidationError(f"{self.name}: must be zero or more {self.unit}, got {value!r}")
        if self.maximum is not None and value > self.maximum:
            raise ValidationError(f"{self.name}: must be at most {self.maximum:g} {self.unit}")
        return float(value)


@dataclass(frozen=True)
class ChoiceListAttribute:
    """A set of values from a fixed vocabulary (cameras, environments)."""

    name: str
    choices: tuple[str, ...]
    label: str
    required: bool = True
    allow_empty: bool = True

    def clean(self, value: Any) -> list[str]:
        if value in ("none", None) and self.allow_empty:
            return []
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise ValidationError(f"{self.name}: must be a list of {', '.join(self.choices)}")
        unknown = sorted(set(value) - set(self.choices))
        if unknown:
            raise ValidationError(
                f"{self.name}: unknown value(s) {', '.join(unknown)}; "
                f"allowed: {', '.join(self.choices)}"
            )
        if not value and not self.allow_empty:
            raise ValidationError(f"{self.name}: at least one of {', '.join(self.choices)}")
        return sorted(set(value))


Attribute = NumberAttribute | ChoiceListAttribute

ATTRIBUTES: dict[str, Attribute] = {
    a.name: a
    for a in (
        NumberAttribute("endurance_min", "min", "Endurance"),
        NumberAttribute("max_range_m", "m", "Maximum range (there and back)"),
        NumberAttribute("max_altitude_m", "m", "Maximum altitude"),
        NumberAttribute("max_speed_mps", "m/s", "Maximum speed"),
        NumberAttribute("max_payload_kg", "kg", "Maximum payload"),
        ChoiceListAttribute("cameras", CAMERAS, "Cameras"),
        NumberAttribute("camera_range_m", "m", "Camera range"),
        # The RGB camera's optics, for a service that plans pictures (the altitude
        # and the photos' spacing over an area): the horizontal field of view and the
        # picture's size (square pixels: the vertical field follows from the aspect).
        NumberAttribute(
            "camera_hfov_deg", "°", "Camera horizontal field of view", False, maximum=170
        ),
        NumberAttribute("camera_width_px", "px", "Camera picture width", False, maximum=100_000),
        NumberAttribute("camera_height_px", "px", "Camera picture height", False, maximum=100_000),
        ChoiceListAttribute("environments", ENVIRONMENTS, "Environments", allow_empty=False),
    )
}

# Optional equipment flags a vehicle may declare (true/false), e.g. the car's camera arm.
FEATURES = ("camera_arm", "obstacle_sensor", "payload_release", "gps")


def attributes_clean(values: Mapping[str, Any]) -> dict[str, Any]:
    """Validate a vehicle's declared attributes.

    Returns the normalised mapping (numbers as floats, lists sorted). Raises
    ``ValidationError`` whose messages each name the offending field; unknown names are
    refused too, so a typo does not silently drop a constraint.
    """
    if not isinstance(values, Mapping):
        raise ValidationError("attributes: must be an object")
    errors: list[str] = []
    cleaned: dict[str, Any] = {}
    for name, value in values.items():
        if name == "features":
            try:
                cleaned["features"] = features_clean(value)
            except ValidationError as exc:
                errors.extend(exc.messages)
            continue
        spec = ATTRIBUTES.get(name)
        if spec is None:
            errors.append(f"{name}: unknown attribute; known: {', '.join(ATTRIBUTES)}, features")
            continue
        try:
            cleaned[name] = spec.clean(value)
        except ValidationError as exc:
            errors.extend(exc.messages)
    for name, spec in ATTRIBUTES.items():
        if spec.required and name not in values:
            errors.append(f"{name}: required")
    optics = [name for name in CAMERA_OPTICS if name in values]
    if optics and len(optics) != len(CAMERA_OPTICS):
        missing = ", ".join(n for n in CAMERA_OPTICS if n not in values)
        errors.append(f"{optics[0]}: declared without {missing} (the camera's optics go together)")
    for name in CAMERA_OPTICS:
        if cleaned.get(name) == 0:
            errors.append(f"{name}: must be more than 0")
    if errors:
        raise ValidationError(errors)
    return cleaned


#: The camera's optics: declared all together, or not at all.
CAMERA_OPTICS = ("camera_hfov_deg", "camera_width_px", "camera_height_px")


@dataclass(frozen=True)
class CameraOptics:
    """A vehicle's declared RGB camera: horizontal field of view and picture size."""

    hfov_deg: float
    width_px: int
    height_px: int

    @property
    def vfov_deg(self) -> float:
        """The vertical field of view (square pixels)."""
        half = math.radians(self.hfov_deg) / 2
        return math.degrees(2 * math.atan(math.tan(half) * self.height_px / self.width_px))

    def footprint_m(self, altitude_m: float) -> tuple[float, float]:
        """Ground width and height a nadir picture covers from ``altitude_m`` (flat)."""
        width = 2 * altitude_m * math.tan(math.radians(self.hfov_deg) / 2)
        return width, width * self.height_px / self.width_px

    def altitude_for_m(self, gsd_m: float) -> float:
        """The altitude at which one pixel covers ``gsd_m`` metres of ground."""
        return gsd_m * self.width_px / (2 * math.tan(math.radians(self.hfov_deg) / 2))


def camera_optics(attributes: Mapping[str, Any]) -> CameraOptics | None:
    """The camera a vehicle declares (its ``attributes``), None when it declares none."""
    try:
        hfov, width, height = (float(attributes[name]) for name in CAMERA_OPTICS)
    except (KeyError, TypeError, ValueError):
        return None
    if not (0 < hfov < 180 and width >= 1 and height >= 1):
        return None
    return CameraOptics(hfov, round(width), round(height))


def features_clean(value: Any) -> list[str]:
    """Validate a list of feature flags; raises ValidationError naming ``features``."""
    if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
        raise ValidationError("features: must be a list of names")
    unknown = sorted(set(value) - set(FEATURES))
    if unknown:
        raise ValidationError(
            f"features: unknown value(s) {', '.join(unknown)}; allowed: {', '.join(FEATURES)}"
        )
    return sorted(set(value))


class DeclaredAttributes:
    """The list-valued declared attributes, read from ``self.attributes``: shared by the
    vehicle model and the plain rows matching works on (services.sessions.matching.Facts)."""

    attributes: dict[str, Any]

    @property
    def cameras(self) -> list[str]:
        return list(self.attributes.get("cameras", []))

    @property
    def features(self) -> list[str]:
        return list(self.attributes.get("features", []))


@deconstructible
class ChoiceListValidator:
    """Model-field validator: the value is a list drawn from ``choices``."""

    def __init__(self, field: str, choices: tuple[str, ...]) -> None:
        self.field = field
        self.choices = tuple(choices)

    def __call__(self, value: Any) -> None:
        if not isinstance(value, list) or not all(v in self.choices for v in value):
            raise ValidationError(f"{self.field}: must be a list of {', '.join(self.choices)}")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ChoiceListValidator) and (self.field, self.choices) == (
            other.field,
            other.choices,
        )

    def __hash__(self) -> int:
        return hash((self.field, self.choices))
