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
    if errors:
        raise ValidationError(errors)
    return cleaned


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
