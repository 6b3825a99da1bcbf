"""The survey's request form: the area drawn on the map, the ground resolution and the
overlaps. It only collects; the kind validates (request.params_clean), as for the API."""

from __future__ import annotations

import json
from typing import Any

from django import forms

from kinds.survey.request import DEFAULT_FRONT, DEFAULT_SIDE


class SurveyRequestForm(forms.Form):
    polygon = forms.CharField(
        widget=forms.HiddenInput, error_messages={"required": "Draw the area on the map."}
    )
    gsd_cm = forms.FloatField(label="Ground resolution (cm a pixel)", initial=3.0)
    front_overlap = forms.FloatField(label="Front overlap (%)", initial=DEFAULT_FRONT)
    side_overlap = forms.FloatField(label="Side overlap (%)", initial=DEFAULT_SIDE)

    def clean_polygon(self) -> list[Any]:
        try:
            points = json.loads(self.cleaned_data["polygon"])
        except ValueError:
            raise forms.ValidationError("Draw the area on the map.") from None
        if not isinstance(points, list):
            raise forms.ValidationError("Draw the area on the map.")
        return points

    def params(self) -> dict[str, Any]:
        data = self.cleaned_data
        return {
            "polygon": data["polygon"],
            "gsd_cm": data["gsd_cm"],
            "front_overlap": data["front_overlap"],
            "side_overlap": data["side_overlap"],
        }
