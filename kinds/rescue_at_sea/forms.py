"""The rescue's request form: the search area drawn on the map, and the altitude."""

from __future__ import annotations

import json
from typing import Any

from django import forms


class RescueRequestForm(forms.Form):
    """A rescue request: the search area drawn on the map, and the search altitude."""

    area = forms.CharField(
        widget=forms.HiddenInput,
        error_messages={"required": "Draw the search area on the map (at least 3 points)."},
    )
    altitude_m = forms.FloatField(
        required=False,
        min_value=1,
        max_value=500,
        label="Search altitude (m)",
        help_text="Higher sees a wider strip per pass; lower sees a person more clearly.",
    )

    def clean_area(self) -> Any:
        raw = self.cleaned_data["area"]
        if len(raw) > 20_000:
            raise forms.ValidationError("The area has too many points.")
        try:
            return json.loads(raw)
        except ValueError:
            raise forms.ValidationError("The area is not valid JSON.") from None
