"""API tokens: issue, authenticate, revoke; the admin pages and the management command."""

from __future__ import annotations

import hashlib
from datetime import timedelta
from io import StringIO

import pytest
import time_machine
from django.contrib.admin.models import LogEntry
from django.core.management import CommandError, call_command
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from accounts.models import ApiToken
from accounts.roles import ADMIN, CLIENT, MONITOR
from accounts.tokens import (
    token_authenticate,
    token_for_raw,
    token_issue,
    token_parse,
    token_revoke,
)
from tests import factories as f

pytestmark = pytest.mark.django_db


@pytest.fixture
def alice():
    return f.user(username="alice", roles=(CLIENT,))


def test_issue_returns_the_token_once_and_stores_only_a_digest(alice):
    raw = token_issue(user=alice, name="  rescue app ")
    scheme, prefix, secret = raw.split("_", 2)
    assert scheme == "iouv" and len(prefix) == 10 and len(secret) >= 43
    token = ApiToken.objects.get()
    assert (token.user, token.name, token.prefix) == (alice, "rescue app", prefix)
    assert token.digest == hashlib.sha256(secret.encode()).hexdigest()
    assert secret not in token.digest and raw not in str(token.__dict__)
    assert token.display == f"iouv_{prefix}_…" and token.is_active
    assert token_for_raw(raw) == token


def test_each_token_is_different(alice):
    assert token_issue(user=alice, name="a") != token_issue(user=alice, name="a")
    assert ApiToken.objects.count() == 2


def test_a_token_needs_a_name(alice):
    with pytest.raises(ValueError, match="name"):
        token_issue(user=alice, name="  ")


def test_authenticate_returns_the_user_and_records_the_use(alice):
    raw = token_issue(user=alice, name="app")
    assert ApiToken.objects.get().last_used_at is None
    assert token_authenticate(raw) == alice
    assert ApiToken.objects.get().last_used_at is not None


def test_last_used_is_written_at_most_once_a_minute(alice):
    raw = token_issue(user=alice, name="app")
    start = timezone.now()
    with time_machine.travel(start, tick=False):
        token_authenticate(raw)
    with time_machine.travel(start + timedelta(seconds=59), tick=False):
        token_authenticate(raw)
        assert ApiToken.objects.get().last_used_at == start
    with time_machine.travel(start + timedelta(seconds=61), tick=False):
        token_authenticate(raw)
        assert ApiToken.objects.get().last_used_at == start + timedelta(seconds=61)


@pytest.mark.parametrize(
    "raw",
    [
        "",
        "iouv",
        "iouv__",
        "bearer",
        "iouv_zzzzzzzzzz_secret",  # prefix not hex
        "iouv_abc_secret",  # prefix too short
        "pat_0123456789_secret",  # another scheme
        "x" * 1000,
        None,
        42,
    ],
)
def test_malformed_tokens_are_refused(alice, raw):
    token_issue(user=alice, name="app")
    assert token_parse(raw) is None
    assert token_authenticate(raw) is None


def test_a_forged_secret_with_a_real_prefix_is_refused(alice):
    raw = token_issue(user=alice, name="app")
    prefix = raw.split("_", 2)[1]
    assert token_authenticate(f"iouv_{prefix}_{'A' * 43}") is None
    assert token_authenticate(raw[:-1]) is None
    assert token_authenticate(raw + "x") is None


def test_an_unknown_prefix_is_refused(alice):
    raw = token_issue(user=alice, name="app")
    _, prefix, secret = raw.split("_", 2)
    other = f"{(int(prefix, 16) + 1) % 16**10:010x}"
    assert token_authenticate(f"iouv_{other}_{secret}") is None


def test_a_revoked_token_stops_working_and_keeps_its_revocation_time(alice):
    raw = token_issue(user=alice, name="app")
    token = token_for_raw(raw)
    token_revoke(token=token)
    first = token.revoked_at
    assert first is not None and not token.is_active
    assert token_authenticate(raw) is None
    token_revoke(token=token)
    assert token.revoked_at == first


def test_revoking_one_token_leaves_the_others(alice):
    keep = token_issue(user=alice, name="keep")
    token_revoke(token=token_for_raw(token_issue(user=alice, name="drop")))
    assert token_authenticate(keep) == alice


def test_an_inactive_users_token_is_refused(alice):
    raw = token_issue(user=alice, name="app")
    alice.is_active = False
    alice.save()
    assert token_authenticate(raw) is None


# --- management command -------------------------------------------------------------------


def test_the_command_prints_a_working_token_once(alice):
    out, err = StringIO(), StringIO()
    call_command("token_issue", "alice", "--name", "ci", stdout=out, stderr=err)
    raw = out.getvalue().strip()
    assert token_authenticate(raw) == alice
    assert ApiToken.objects.get().name == "ci"
    assert "once" in err.getvalue() and raw not in err.getvalue()


def test_the_command_refuses_an_unknown_user():
    with pytest.raises(CommandError, match="no user"):
        call_command("token_issue", "nobody", "--name", "ci", stdout=StringIO())


# --- admin ------------------------------------------------------------------------------------


@pytest.fixture
def as_admin():
    f.user(username="root", roles=(ADMIN,))
    client = Client()
    assert client.login(username="root", password="pw-for-tests")
    return client


def test_admin_issues_a_token_and_shows_it_once(as_admin, alice):
    response = as_admin.post(
        reverse("admin:accounts_apitoken_add"), {"user": alice.pk, "name": "partner app"}
    )
    assert response.status_code == 200
    assert "no-store" in response["Cache-Control"]
    token = ApiToken.objects.get()
    page = response.content.decode()
    raw = page.split('<code class="api-token">')[1].split("</code>")[0]
    assert token_authenticate(raw) == alice and token.name == "partner app"
    # Nowhere else: not in the admin log, not in the messages kept for the next page.
    assert all(raw not in (e.change_message + e.object_repr) for e in LogEntry.objects.all())
    assert raw not in as_admin.get(reverse("admin:accounts_apitoken_changelist")).content.decode()
    assert raw not in str(dict(as_admin.session))


def test_admin_lists_tokens_by_prefix_and_revokes_them(as_admin, alice):
    raw = token_issue(user=alice, name="app")
    token = token_for_raw(raw)
    page = as_admin.get(reverse("admin:accounts_apitoken_changelist")).content.decode()
    assert token.display in page and raw not in page
    response = as_admin.post(
        reverse("admin:accounts_apitoken_changelist"),
        {"action": "revoke", "_selected_action": [token.pk]},
        follow=True,
    )
    assert "Revoked 1 token" in response.content.decode()
    assert token_authenticate(raw) is None
    # The row stays, as a record; it cannot be deleted from the admin.
    delete = as_admin.get(reverse("admin:accounts_apitoken_delete", args=[token.pk]))
    assert delete.status_code == 403


def test_an_issued_token_cannot_be_edited(as_admin, alice):
    token = token_for_raw(token_issue(user=alice, name="app"))
    page = as_admin.get(reverse("admin:accounts_apitoken_change", args=[token.pk]))
    assert page.status_code == 200
    assert 'name="name"' not in page.content.decode()


def test_monitors_cannot_see_tokens(alice):
    f.user(username="mon", roles=(MONITOR,))
    client = Client()
    client.login(username="mon", password="pw-for-tests")
    assert client.get(reverse("admin:accounts_apitoken_changelist")).status_code == 403


def test_the_admin_finds_the_tokens_user_by_name_not_by_a_raw_id(as_admin, alice):
    page = as_admin.get(reverse("admin:accounts_apitoken_add")).content.decode()
    assert "vForeignKeyRawIdAdminField" not in page  # no raw id to type
    assert 'class="admin-autocomplete' in page and 'name="user"' in page
    # Typing part of the name finds the user.
    found = as_admin.get(
        reverse("admin:autocomplete"),
        {"app_label": "accounts", "model_name": "apitoken", "field_name": "user", "term": "ali"},
    ).json()
    assert [r["text"] for r in found["results"]] == [alice.get_username()]
