"""The rescue's rows in the admin: each station's rescue team."""

from __future__ import annotations

from django.contrib import admin

from kinds.rescue_at_sea.models import RescueTeam


@admin.register(RescueTeam)
class RescueTeamAdmin(admin.ModelAdmin[RescueTeam]):
    list_display = ("station", "name", "email", "phone", "webhook")
    search_fields = ("station__name", "name", "email")
