"""The delivery's request form: the two points picked on the map, the weight, and who
receives it. It only collects; the kind validates (request.params_clean), as for the
API."""

from __future__ import annotations

import json
from typing import Any

from django import forms


def _point(raw: str, what: str) -> dict[str, Any]:
    try:
        lat, lon = json.loads(raw)
        return {"lat": float(lat), "lon": float(lon)}
    except (ValueError, TypeError):
        raise forms.ValidationError(f"Pick the {what} on the map.") from None


class ParcelRequestForm(forms.Form):
    pickup = forms.CharField(
        widget=forms.HiddenInput, error_messages={"required": "Pick the pickup on the map."}
    )
    dropoff = forms.CharField(
        widget=forms.HiddenInput, error_messages={"required": "Pick the drop-off on the map."}
    )
    weight_kg = forms.FloatField(label="Weight (kg)", min_value=0.01, initial=0.5)
    recipient_name = forms.CharField(label="Recipient's name", required=False, max_length=100)
    recipient_email = forms.EmailField(
        label="Recipient's e-mail",
        required=False,
        help_text="They get the tracking link when the parcel is on its way.",
    )
    recipient_webhook = forms.URLField(
        label="Recipient's webhook (optional)",
        required=False,
        max_length=300,
        # A scheme-less address is taken as https, never plain http.
        assume_scheme="https",
    )

    def clean_pickup(self) -> dict[str, Any]:
        return _point(self.cleaned_data["pickup"], "pickup")

    def clean_dropoff(self) -> dict[str, Any]:
        return _point(self.cleaned_data["dropoff"], "drop-off")

    def params(self) -> dict[str, Any]:
        data = self.cleaned_data
        recipient = {
            key: data[f"recipient_{key}"]
            for key in ("name", "email", "webhook")
            if data.get(f"recipient_{key}")
        }
        return {
            "pickup": data["pickup"],
            "dropoff": data["dropoff"],
            "weight_kg": data["weight_kg"],
            "recipient": recipient,
        }
