"""Admin forms for the fleet: JSON fields explained and checked before they are stored."""

from __future__ import annotations

import json
from typing import Any

from django import forms
from django.core.exceptions import ValidationError

from agents.protocol import ProtocolError
from agents.protocol.messages import encode_message, message_from_dict
from fleet.attributes import ATTRIBUTES, FEATURES, ChoiceListAttribute
from fleet.models import Vehicle, VehicleType


def attributes_help() -> str:
    """One line per declared attribute with its unit or allowed values, for the form."""
    parts = []
    for spec in ATTRIBUTES.values():
        if isinstance(spec, ChoiceListAttribute):
            parts.append(f"{spec.name}: list of {', '.join(spec.choices)}")
        else:
            optional = "" if spec.required else ", optional"
            parts.append(f"{spec.name} ({spec.unit}{optional})")
    parts.append(f"features (optional): list of {', '.join(FEATURES)}")
    return "A JSON object with " + "; ".join(parts) + "."


class VehicleAdminForm(forms.ModelForm[Vehicle]):
    """The declared part of a vehicle. ``attributes`` is validated by ``Vehicle.clean``
    (``fleet.attributes.attributes_clean``) during model validation, whose messages each
    name the offending attribute; it is not checked a second time here so each problem
    is reported once."""

    class Meta:
        model = Vehicle
        fields = ("name", "vehicle_type", "station", "attributes")
        widgets = {"attributes": forms.Textarea(attrs={"rows": 14, "cols": 70})}

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if "attributes" in self.fields:
            self.fields["attributes"].help_text = attributes_help()
            if not self.instance.attributes:
                # A complete template is easier to fill in than an empty {}.
                self.initial.setdefault("attributes", _attributes_template())


def _attributes_template() -> dict[str, Any]:
    return {
        name: ([] if isinstance(spec, ChoiceListAttribute) else 0)
        for name, spec in ATTRIBUTES.items()
        if spec.required
    } | {"features": []}


def commands_validate(commands: Any) -> None:
    """Check a command vocabulary exactly as a browser client will receive it.

    Raises ValidationError naming the offending entry (e.g. ``commands[2].args.speed.min``).
    """
    # The vocabulary travels in the control channel's welcome message; validating it as
    # that message reuses the wire protocol's own rules and size limit.
    message = {
        "type": "welcome",
        "role": "viewer",
        "vehicle": {},
        "commands": commands,
        "telemetry": [],
    }
    try:
        welcome = message_from_dict(message, channel="control_to_client")
        encode_message(welcome, channel="control_to_client")  # and within the size limit
    except ProtocolError as exc:
        raise ValidationError(exc.message.removeprefix("welcome message: ")) from None


class VehicleTypeAdminForm(forms.ModelForm[VehicleType]):
    """A vehicle type, with its declared command vocabulary checked against the protocol."""

    class Meta:
        model = VehicleType
        fields = ("name", "kind", "adapter", "description", "commands")
        widgets = {"commands": forms.Textarea(attrs={"rows": 20, "cols": 90})}

    def clean_commands(self) -> Any:
        commands = self.cleaned_data["commands"]
        if commands is None:  # an emptied text box means "no declared commands"
            commands = []
        commands_validate(commands)
        return commands


def json_pretty(value: Any) -> str:
    """Indented JSON for read-only display."""
    return json.dumps(value, indent=2, sort_keys=True, default=str)
