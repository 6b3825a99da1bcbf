"""Django admin for API tokens: list, issue (shown once) and revoke.

Thin: issuing and revoking go through accounts.tokens. The plain token goes only into
the one response that shows it: not into the messages framework (which keeps messages
in the session or a cookie), not into the admin log.
"""

from __future__ import annotations

from typing import Any

from django import forms
from django.contrib import admin, messages
from django.db.models import QuerySet
from django.http import HttpRequest, HttpResponse
from django.template import engines
from django.utils.cache import add_never_cache_headers

from accounts.models import ApiToken
from accounts.tokens import token_for_raw, token_issue, token_revoke

# Kept here rather than in a template file: this page is part of the issue flow and
# nothing else renders it.
_ISSUED_PAGE = """{% extends "admin/base_site.html" %}
{% load admin_urls %}
{% block bodyclass %}{{ block.super }} app-accounts model-apitoken{% endblock %}
{% block breadcrumbs %}
<div class="breadcrumbs">
<a href="{% url 'admin:index' %}">Home</a>
&rsaquo; <a href="{% url opts|admin_urlname:'changelist' %}">
  {{ opts.verbose_name_plural|capfirst }}</a>
&rsaquo; New token
</div>
{% endblock %}
{% block content %}
<p class="errornote">
  Copy this token now: it is shown only once and cannot be recovered.
</p>
<table>
  <tr><th>User</th><td>{{ token.user }}</td></tr>
  <tr><th>Name</th><td>{{ token.name }}</td></tr>
  <tr><th>Token</th><td><code class="api-token">{{ raw }}</code></td></tr>
</table>
<p>Send it as <code>Authorization: Bearer &lt;token&gt;</code> (see docs/api.md).</p>
<p><a href="{% url opts|admin_urlname:'changelist' %}" class="button">Done</a></p>
{% endblock %}
"""


class ApiTokenIssueForm(forms.ModelForm[ApiToken]):
    class Meta:
        model = ApiToken
        fields = ("user", "name")


@admin.register(ApiToken)
class ApiTokenAdmin(admin.ModelAdmin[ApiToken]):
    list_display = ("name", "user", "display", "created_at", "last_used_at", "revoked_at")
    list_filter = (("revoked_at", admin.EmptyFieldListFilter),)
    list_select_related = ("user",)
    search_fields = ("name", "prefix", "user__username")
    # Found by typing a name (the user admin's search), not by a raw user id.
    autocomplete_fields = ("user",)
    actions = ("revoke",)
    readonly_fields = ("user", "name", "display", "created_at", "last_used_at", "revoked_at")

    def get_form(
        self, request: HttpRequest, obj: ApiToken | None = None, change: bool = False, **kwargs: Any
    ) -> type[forms.ModelForm[ApiToken]]:
        if obj is None:
            kwargs["form"] = ApiTokenIssueForm
        return super().get_form(request, obj, change, **kwargs)

    def get_readonly_fields(self, request: HttpRequest, obj: Any = None) -> Any:
        # Issuing asks for a user and a name; an issued token is never edited.
        return () if obj is None else self.readonly_fields

    def get_fields(self, request: HttpRequest, obj: Any = None) -> Any:
        return ("user", "name") if obj is None else self.readonly_fields

    def has_delete_permission(self, request: HttpRequest, obj: Any = None) -> bool:
        # Revoke instead: the row stays as a record of who held a token and when.
        return False

    @admin.display(description="token")
    def display(self, obj: ApiToken) -> str:
        return obj.display

    def save_model(self, request: HttpRequest, obj: ApiToken, form: Any, change: bool) -> None:
        if change:  # pragma: no cover - every field is read-only once issued
            return
        raw = token_issue(user=obj.user, name=obj.name)
        issued = token_for_raw(raw)
        assert issued is not None
        obj.pk = issued.pk
        obj.refresh_from_db()
        # Held on the request only, for response_add below.
        request._issued_api_token = raw  # type: ignore[attr-defined]

    def response_add(self, request: HttpRequest, obj: ApiToken, *args: Any) -> HttpResponse:
        raw = getattr(request, "_issued_api_token", None)
        if raw is None:  # pragma: no cover
            return super().response_add(request, obj, *args)
        context = {
            **self.admin_site.each_context(request),
            "title": "New API token",
            "opts": self.opts,
            "token": obj,
            "raw": raw,
        }
        page = engines["django"].from_string(_ISSUED_PAGE).render(context, request)
        response = HttpResponse(page)
        add_never_cache_headers(response)
        return response

    @admin.action(description="Revoke selected tokens", permissions=["change"])
    def revoke(self, request: HttpRequest, queryset: QuerySet[ApiToken]) -> None:
        count = 0
        for token in queryset.filter(revoked_at__isnull=True):
            token_revoke(token=token)
            self.log_change(request, token, "Revoked.")
            count += 1
        self.message_user(request, f"Revoked {count} token(s).", messages.SUCCESS)
