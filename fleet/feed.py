"""Pushes fleet changes to the monitors' live feed over the channel layer."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from operations.layer import group_send_after_commit

FLEET_GROUP = "fleet"


def fleet_notify(vehicle_ids: Iterable[Any]) -> None:
    """After the current transaction commits, tell the feed which vehicles changed.

    Only ids travel: each feed consumer reads the committed rows itself, so a rolled
    back change is never shown.
    """
    ids = [str(pk) for pk in vehicle_ids]
    if not ids:
        return

    group_send_after_commit(FLEET_GROUP, {"type": "fleet.changed", "ids": ids})
