"""Django admin for services, and a read-only view of sessions and their logs.

Sessions, assignments and session events are made by the platform (services.sessions.states,
services.sessions.matching, services.sessions.log); the admin only shows them.
"""

from __future__ import annotations

from typing import Any

from django.contrib import admin, messages
from django.db.models import QuerySet
from django.http import HttpRequest
from django.utils.html import format_html

from fleet.admin import UUIDSearchMixin
from fleet.forms import json_pretty
from services.models import Assignment, Service, ServiceGrant, ServiceRole, Session, SessionEvent
from services.records.keeping import record_delete
from services.sessions.log import session_log_verify


class ReadOnlyAdminMixin:
    """No add, change or delete, whoever asks (superusers included)."""

    def has_add_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        return False


class ServiceRoleInline(admin.StackedInline[ServiceRole, Service]):
    model = ServiceRole
    extra = 0
    fields = (
        ("name", "required", "selection"),
        ("kinds", "adapters"),
        ("cameras", "environments", "features"),
        ("min_attributes", "min_battery"),
    )


class ServiceGrantInline(admin.TabularInline[ServiceGrant, Service]):
    model = ServiceGrant
    extra = 0
    fields = ("group", "user")
    raw_id_fields = ("user",)


@admin.register(Service)
class ServiceAdmin(admin.ModelAdmin[Service]):
    list_display = ("slug", "name", "kind", "is_active")
    list_filter = ("kind", "is_active")
    search_fields = ("slug", "name")
    prepopulated_fields = {"slug": ("name",)}
    inlines = (ServiceRoleInline, ServiceGrantInline)
    fieldsets = (
        (None, {"fields": ("slug", "name", "description", "kind", "is_active")}),
        (
            "Commands and limits (signed into every vehicle task)",
            {
                "fields": (
                    "allowed_commands",
                    ("max_altitude_m", "geofence_radius_m", "max_speed_mps"),
                    ("failsafe_action", "link_loss_timeout_ms"),
                    "session_time_limit_s",
                    ("latency_soft_ms", "latency_hard_ms"),
                )
            },
        ),
    )


class AssignmentInline(ReadOnlyAdminMixin, admin.TabularInline[Assignment, Session]):
    model = Assignment
    extra = 0
    fields = ("role", "vehicle", "active", "distance_m", "created_at", "released_at")
    readonly_fields = fields


class SessionEventInline(ReadOnlyAdminMixin, admin.TabularInline[SessionEvent, Session]):
    model = SessionEvent
    extra = 0
    fields = ("seq", "kind", "event_data", "occurred_at", "created_at", "hash")
    readonly_fields = fields
    ordering = ("seq",)

    @admin.display(description="data")
    def event_data(self, obj: SessionEvent) -> str:
        return format_html("<pre>{}</pre>", json_pretty(obj.data))


@admin.register(Session)
class SessionAdmin(UUIDSearchMixin, ReadOnlyAdminMixin, admin.ModelAdmin[Session]):
    list_display = ("id", "service", "user", "state", "reason", "created_at")
    list_filter = ("state", "service")
    list_select_related = ("service", "user")
    search_fields = ("user__username", "user__email")
    date_hierarchy = "created_at"
    fields = (
        "id",
        "service",
        "user",
        "state",
        "reason",
        "log_chain",
        ("target_lat", "target_lon"),
        "params",
        "relay",
        ("created_at", "assigned_at", "started_at", "ended_at"),
    )
    # All of it: sessions change only through services.sessions.states.
    readonly_fields = tuple(
        name for entry in fields for name in (entry if isinstance(entry, tuple) else (entry,))
    )
    inlines = (AssignmentInline, SessionEventInline)
    actions = ("delete_flight_records",)

    @admin.action(description="Delete the flight records of the selected sessions")
    def delete_flight_records(self, request: HttpRequest, queryset: QuerySet[Session]) -> None:
        # Only the record goes: the session and its log stay, and the log says who
        # deleted the record (services.records.keeping.record_delete).
        if not request.user.is_superuser:
            self.message_user(request, "Only an administrator may delete records.", messages.ERROR)
            return
        samples = sum(
            record_delete(session=session, by=request.user.get_username()) for session in queryset
        )
        self.message_user(request, f"Deleted {samples} samples of flight records.")

    @admin.display(description="log chain")
    def log_chain(self, obj: Session) -> str:
        # Recomputed on every view (not in the list: it reads the whole log).
        check = session_log_verify(session=obj)
        if check.ok:
            return f"OK with {check.events} events"
        return f"broken at #{check.bad_seq}: {check.problem}"


@admin.register(SessionEvent)
class SessionEventAdmin(UUIDSearchMixin, ReadOnlyAdminMixin, admin.ModelAdmin[SessionEvent]):
    list_display = ("session", "seq", "kind", "occurred_at", "created_at")
    list_filter = ("kind",)
    list_select_related = ("session__service", "session__user")
    search_fields = ("kind", "session__user__username")
    uuid_search_fields = ("session_id",)
    fields = ("session", "seq", "kind", "data", "occurred_at", "created_at", "prev_hash", "hash")
    ordering = ("-pk",)


@admin.register(Assignment)
class AssignmentAdmin(UUIDSearchMixin, ReadOnlyAdminMixin, admin.ModelAdmin[Assignment]):
    list_display = ("vehicle", "role", "session", "active", "created_at", "released_at")
    list_filter = ("active", "role")
    list_select_related = ("vehicle", "session__service", "session__user")
    search_fields = ("vehicle__name", "role")
    uuid_search_fields = ("session_id", "vehicle_id")
