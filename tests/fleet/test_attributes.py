"""Declared attributes are validated and a refusal names the field."""

from __future__ import annotations

import pytest
from django.core.exceptions import ValidationError

from fleet.attributes import attributes_clean, camera_optics
from tests import factories as f


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"max_range_m": -5}, "max_range_m"),
        ({"cameras": ["rgb", "xray"]}, "cameras"),
        ({"max_payload_kg": "heavy"}, "max_payload_kg"),
        ({"max_speed_mps": True}, "max_speed_mps"),
        ({"endurance_min": float("nan")}, "endurance_min"),
        ({"environments": []}, "environments"),
        ({"environments": ["space"]}, "environments"),
        ({"colour": "red"}, "colour"),
        ({"features": ["laser"]}, "features"),
        (
            {"camera_hfov_deg": 190, "camera_width_px": 640, "camera_height_px": 480},
            "camera_hfov_deg",
        ),
        ({"camera_hfov_deg": 60, "camera_width_px": 0, "camera_height_px": 480}, "camera_width_px"),
        ({"camera_hfov_deg": 60}, "camera_hfov_deg"),
    ],
)
def test_bad_value_is_refused_naming_the_field(change, field):
    with pytest.raises(ValidationError) as refused:
        attributes_clean({**f.DRONE_ATTRS, **change})
    assert any(m.startswith(f"{field}:") for m in refused.value.messages), refused.value.messages


def test_missing_attribute_is_named():
    attrs = dict(f.DRONE_ATTRS)
    del attrs["max_altitude_m"]
    with pytest.raises(ValidationError, match="max_altitude_m: required"):
        attributes_clean(attrs)


def test_good_values_are_normalised():
    cleaned = attributes_clean(
        {**f.DRONE_ATTRS, "cameras": ["thermal", "rgb", "rgb"], "max_payload_kg": 2}
    )
    assert cleaned["cameras"] == ["rgb", "thermal"]
    assert cleaned["max_payload_kg"] == 2.0
    assert attributes_clean({**f.DRONE_ATTRS, "cameras": "none"})["cameras"] == []


@pytest.mark.django_db
def test_vehicle_full_clean_refuses_under_attributes():
    st, vt = f.station(), f.vehicle_type()
    with pytest.raises(ValidationError) as refused:
        f.vehicle(station=st, vtype=vt, max_range_m=-1)
    assert "attributes" in refused.value.message_dict
    assert "max_range_m" in refused.value.message_dict["attributes"][0]


def test_a_camera_declares_its_optics_and_a_service_can_plan_pictures_with_them():
    cleaned = attributes_clean(
        {**f.DRONE_ATTRS, "camera_hfov_deg": 90, "camera_width_px": 1000, "camera_height_px": 500}
    )
    optics = camera_optics(cleaned)
    assert optics is not None and (optics.width_px, optics.height_px) == (1000, 500)
    # 90° across: the ground is twice the altitude wide, half as tall (2:1 picture).
    assert optics.footprint_m(50) == pytest.approx((100, 50))
    assert optics.altitude_for_m(0.05) == pytest.approx(25)  # 5 cm a pixel, 1000 px = 50 m
    assert optics.vfov_deg == pytest.approx(53.13, abs=0.01)
    # A vehicle declaring no optics has none to plan with (they are optional).
    assert camera_optics(attributes_clean(f.DRONE_ATTRS)) is None
