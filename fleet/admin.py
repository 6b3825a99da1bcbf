"""Django admin for the fleet. Thin: the actions call fleet.credentials and fleet.status."""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from django.contrib import admin, messages
from django.db.models import Count, Q, QuerySet
from django.http import HttpRequest, HttpResponse
from django.template.response import TemplateResponse
from django.utils.cache import add_never_cache_headers
from django.utils.html import format_html

from fleet.credentials import vehicle_issue_credential
from fleet.forms import VehicleAdminForm, VehicleTypeAdminForm, json_pretty
from fleet.liveness import Live, vehicles_live
from fleet.models import Station, Vehicle, VehicleType
from fleet.status import FleetError, vehicle_set_maintenance


class UUIDSearchMixin:
    """Admin search that also finds rows by a pasted UUID.

    The stock ``=id`` search compares the UUID as text, which differs between SQLite
    (no dashes) and PostgreSQL; parsing the term and comparing UUIDs works on both.
    """

    uuid_search_fields: tuple[str, ...] = ("pk",)

    def get_search_results(
        self, request: HttpRequest, queryset: QuerySet[Any], search_term: str
    ) -> tuple[QuerySet[Any], bool]:
        found, may_have_duplicates = super().get_search_results(  # type: ignore[misc]
            request, queryset, search_term
        )
        try:
            value = uuid.UUID(search_term.strip())
        except ValueError:
            return found, may_have_duplicates
        by_id = Q()
        for name in self.uuid_search_fields:
            by_id |= Q(**{name: value})
        return found | queryset.filter(by_id), may_have_duplicates


@admin.register(Station)
class StationAdmin(admin.ModelAdmin[Station]):
    list_display = ("name", "lat", "lon", "environments", "vehicle_count")
    search_fields = ("name",)
    fields = ("name", "lat", "lon", "environments")

    def get_queryset(self, request: HttpRequest) -> QuerySet[Station]:
        return super().get_queryset(request).annotate(_vehicle_count=Count("vehicles"))

    @admin.display(description="vehicles", ordering="_vehicle_count")
    def vehicle_count(self, obj: Station) -> int:
        count: int = obj._vehicle_count  # type: ignore[attr-defined]  # get_queryset's annotation
        return count


@admin.register(VehicleType)
class VehicleTypeAdmin(admin.ModelAdmin[VehicleType]):
    form = VehicleTypeAdminForm
    list_display = ("name", "kind", "adapter", "command_count")
    list_filter = ("kind", "adapter")
    search_fields = ("name",)

    @admin.display(description="commands")
    def command_count(self, obj: VehicleType) -> int:
        return len(obj.commands or [])


@dataclass(frozen=True)
class IssuedCredential:
    """One row of the page that shows fresh credentials; never stored."""

    vehicle: Vehicle
    credential: str


@admin.register(Vehicle)
class VehicleAdmin(UUIDSearchMixin, admin.ModelAdmin[Vehicle]):
    form = VehicleAdminForm
    list_display = (
        "name",
        "vehicle_type",
        "station",
        "status",
        "maintenance",
        "battery_level",
        "last_heard",
    )
    list_filter = ("station", "vehicle_type", "status", "maintenance")
    list_select_related = ("vehicle_type", "station")
    search_fields = ("name", "station__name")
    actions = ("issue_credential", "put_in_maintenance", "return_to_service")
    # Live state belongs to the uplink and maintenance to its actions (which refuse a
    # vehicle in a session); the form edits only what the vehicle declares.
    readonly_fields = (
        "id",
        "credential_issued_at",
        "status",
        "maintenance",
        "battery_level",
        "position",
        "last_heard",
        "control_url",
        "reported_profile",
    )
    fieldsets = (
        (None, {"fields": ("name", "vehicle_type", "station", "attributes")}),
        ("Enrolment", {"fields": ("id", "credential_issued_at")}),
        (
            "Live state (reported by the agent)",
            {
                "fields": (
                    "status",
                    "maintenance",
                    "battery_level",
                    "position",
                    "last_heard",
                    "control_url",
                    "reported_profile",
                )
            },
        ),
    )

    # The live fields show what the agent last reported (fleet.liveness): the row is
    # written only when the vehicle's state changes.

    def _live(self, vehicle: Vehicle) -> Live | None:
        if not hasattr(vehicle, "_admin_live"):
            vehicle._admin_live = vehicles_live([vehicle.pk]).get(str(vehicle.pk))  # type: ignore[attr-defined]
        return vehicle._admin_live  # type: ignore[attr-defined,no-any-return]

    @admin.display(description="battery", ordering="battery")
    def battery_level(self, vehicle: Vehicle) -> str:
        live = self._live(vehicle)
        battery = live.battery if live is not None else vehicle.battery
        # Agents report a float (99.59783016905): a person reads whole percents.
        return "\u2013" if battery is None else f"{battery:.0f} %"

    @admin.display(description="position")
    def position(self, obj: Vehicle) -> str:
        live = self._live(obj)
        lat, lon, alt = (live.lat, live.lon, live.alt) if live else (obj.lat, obj.lon, obj.alt)
        if lat is None or lon is None:
            return "not reported (at its station)"
        height = f", {alt:g} m" if alt is not None else ""
        return f"{lat:.6f}, {lon:.6f}{height}"

    @admin.display(description="last heard", ordering="last_seen")
    def last_heard(self, obj: Vehicle) -> datetime | None:
        live = self._live(obj)
        return live.seen_at if live is not None else obj.last_seen

    @admin.display(description="profile")
    def reported_profile(self, obj: Vehicle) -> str:
        if not obj.profile:
            return "-"
        return format_html("<pre>{}</pre>", json_pretty(obj.profile))

    # --- permissions for the actions ---------------------------------------------------

    def has_issue_credential_permission(self, request: HttpRequest) -> bool:
        return request.user.has_perm("fleet.issue_credential")

    def has_set_maintenance_permission(self, request: HttpRequest) -> bool:
        return request.user.has_perm("fleet.set_maintenance")

    # --- actions -------------------------------------------------------------------------

    @admin.action(description="Issue a fresh credential", permissions=["issue_credential"])
    def issue_credential(self, request: HttpRequest, queryset: QuerySet[Vehicle]) -> HttpResponse:
        """Issue credentials and show them on a page rendered once.

        The plain values go only into this response: not into the messages framework
        (which stores them in the session or a cookie), not into the admin log.
        """
        issued = []
        for vehicle in queryset.select_related("vehicle_type", "station"):
            credential = vehicle_issue_credential(vehicle=vehicle)
            self.log_change(request, vehicle, "Issued a fresh credential.")
            issued.append(IssuedCredential(vehicle=vehicle, credential=credential))
        context = {
            **self.admin_site.each_context(request),
            "title": "Fresh vehicle credentials",
            "opts": self.opts,
            "issued": issued,
        }
        response = TemplateResponse(request, "admin/fleet/vehicle/credentials_issued.html", context)
        add_never_cache_headers(response)
        return response

    @admin.action(description="Put in maintenance", permissions=["set_maintenance"])
    def put_in_maintenance(self, request: HttpRequest, queryset: QuerySet[Vehicle]) -> None:
        self._set_maintenance(request, queryset, on=True)

    @admin.action(description="Return to service", permissions=["set_maintenance"])
    def return_to_service(self, request: HttpRequest, queryset: QuerySet[Vehicle]) -> None:
        self._set_maintenance(request, queryset, on=False)

    def _set_maintenance(
        self, request: HttpRequest, queryset: QuerySet[Vehicle], *, on: bool
    ) -> None:
        changed = []
        for vehicle in queryset:
            try:
                vehicle_set_maintenance(vehicle=vehicle, on=on)
            except FleetError as exc:
                # One busy vehicle must not stop the others: report it and go on.
                self.message_user(request, str(exc), level=messages.ERROR)
                continue
            self.log_change(
                request, vehicle, "Put in maintenance." if on else "Returned to service."
            )
            changed.append(vehicle.name)
        if changed:
            what = "Put in maintenance" if on else "Returned to service"
            self.message_user(request, f"{what}: {', '.join(changed)}.", level=messages.SUCCESS)
