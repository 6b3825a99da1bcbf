"""Declared attributes are validated and a refusal names the field."""

from __future__ import annotations

import pytest
from django.core.exceptions import ValidationError

from fleet.attributes import attributes_clean
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
