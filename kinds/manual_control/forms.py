"""The request form of manual control: where, extra vehicle wishes, relay."""

from __future__ import annotations

from typing import Any

from django import forms

from fleet.models import Station
from services.kit import CAMERAS, FEATURES

#: The features a person may ask for, in words.
FEATURE_WORDS = {
    "camera_arm": "a camera arm (pan and tilt)",
    "obstacle_sensor": "an obstacle sensor",
    "payload_release": "a payload release",
    "gps": "GPS",
}


class SessionRequestForm(forms.Form):
    """A service request: where (a point or a station), extra vehicle wishes, relay."""

    station = forms.ModelChoiceField(
        queryset=Station.objects.all(),
        required=False,
        empty_label="Anywhere",
        help_text="Take a vehicle near this station.",
    )
    lat = forms.FloatField(required=False, min_value=-90, max_value=90, label="Latitude")
    lon = forms.FloatField(required=False, min_value=-180, max_value=180, label="Longitude")
    cameras = forms.MultipleChoiceField(
        choices=[(c, c.upper() if c == "rgb" else c) for c in CAMERAS],
        required=False,
        widget=forms.CheckboxSelectMultiple,
        help_text="The vehicle must carry these cameras too.",
    )
    features = forms.MultipleChoiceField(
        choices=[(f, FEATURE_WORDS.get(f, f.replace("_", " "))) for f in FEATURES],
        required=False,
        widget=forms.CheckboxSelectMultiple,
        help_text="The vehicle must have these too.",
    )
    min_battery = forms.FloatField(
        required=False, min_value=0, max_value=100, label="Minimum battery (%)"
    )
    relay = forms.BooleanField(
        required=False,
        label="Control through the platform (relay)",
        help_text="For networks that cannot reach the vehicle directly; adds latency.",
    )

    def clean(self) -> dict[str, Any]:
        super().clean()
        data = self.cleaned_data
        lat, lon = data.get("lat"), data.get("lon")
        if (lat is None) != (lon is None):
            raise forms.ValidationError("Give both latitude and longitude, or neither.")
        return data

    def target(self) -> tuple[float, float] | None:
        data = self.cleaned_data
        if data.get("lat") is not None:
            return (data["lat"], data["lon"])
        station = data.get("station")
        return (station.lat, station.lon) if station else None

    def preferences(self) -> dict[str, Any]:
        prefs: dict[str, Any] = {}
        if self.cleaned_data.get("cameras"):
            prefs["cameras"] = list(self.cleaned_data["cameras"])
        if self.cleaned_data.get("features"):
            prefs["features"] = list(self.cleaned_data["features"])
        if self.cleaned_data.get("min_battery") is not None:
            prefs["min_battery"] = self.cleaned_data["min_battery"]
        return prefs
