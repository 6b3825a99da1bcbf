"""Login lockout (accounts.lockout, django-axes): ten wrong passwords lock the account and
the address for a while, on the portal's login page and on the admin's; a locked-out
attempt is refused before any password is hashed, so a flood stops costing a hash each.

Driven through Django's test client against the real database (axes keeps its attempts
there). Addresses are told apart as nginx tells them (``BEHIND_PROXY``, the last entry of
``X-Forwarded-For``: accounts.addresses)."""

from __future__ import annotations

import datetime as dt
from typing import Any
from unittest import mock

import pytest
import time_machine
from django.contrib.auth.hashers import MD5PasswordHasher
from django.test import Client

from accounts.roles import ADMIN, CLIENT
from tests import factories as f

pytestmark = pytest.mark.django_db

PASSWORD = "pw-for-tests"  # tests.factories.user's
PORTAL = "/accounts/login/"
ADMIN_LOGIN = "/admin/login/"
ATTACKER = "203.0.113.66"
ELSEWHERE = "198.51.100.20"


@pytest.fixture(autouse=True)
def _behind_proxy(settings: Any) -> None:
    settings.BEHIND_PROXY = True
    settings.AXES_FAILURE_LIMIT = 10


def _login(path: str, username: str, password: str, address: str) -> Any:
    """A log-in posted from ``address``; returns the answer (after the form's redirect,
    a logged-in client has a session)."""
    client = Client()
    response = client.post(
        path,
        {"username": username, "password": password, "next": "/"},
        HTTP_X_FORWARDED_FOR=f"10.9.9.9, {address}",  # the first entry is the client's word
    )
    response.logged_in = "_auth_user_id" in client.session
    return response


def _wrong(path: str, username: str, address: str, times: int) -> None:
    for _ in range(times):
        answer = _login(path, username, "not-the-password", address)
        assert answer.status_code == 200 and not answer.logged_in  # the form again


@pytest.mark.parametrize(("path", "roles"), [(PORTAL, (CLIENT,)), (ADMIN_LOGIN, (ADMIN,))])
def test_ten_wrong_passwords_lock_the_account_even_with_the_right_one(path, roles) -> None:
    carol = f.user(username="carol", roles=roles)
    assert carol.is_staff or path == PORTAL
    _wrong(path, "carol", ATTACKER, 9)
    # The tenth is answered with the lockout, and so is the right password after it.
    assert _login(path, "carol", "not-the-password", ATTACKER).status_code == 429
    locked = _login(path, "carol", PASSWORD, ATTACKER)
    assert locked.status_code == 429 and not locked.logged_in
    assert int(locked["Retry-After"]) == 900
    assert b"Too many failed log-ins" in locked.content
    # The account, wherever the attempt comes from.
    assert _login(path, "carol", PASSWORD, ELSEWHERE).status_code == 429
    # For a while: after the cool-off, the right password logs in again.
    with time_machine.travel(dt.datetime.now(dt.UTC) + dt.timedelta(minutes=16)):
        back = _login(path, "carol", PASSWORD, ELSEWHERE)
    assert back.status_code == 302 and back.logged_in


def test_nine_wrong_passwords_then_the_right_one_log_in_and_start_the_count_again() -> None:
    f.user(username="dave")
    _wrong(PORTAL, "dave", ATTACKER, 9)
    assert _login(PORTAL, "dave", PASSWORD, ATTACKER).logged_in
    _wrong(PORTAL, "dave", ATTACKER, 9)  # the success cleared the failures
    assert _login(PORTAL, "dave", PASSWORD, ATTACKER).logged_in


def test_a_flood_from_one_address_is_locked_out_whatever_names_it_tries() -> None:
    f.user(username="erin")
    for n in range(9):
        _wrong(PORTAL, f"guess-{n}", ATTACKER, 1)
    assert _login(PORTAL, "guess-9", "not-the-password", ATTACKER).status_code == 429
    # The address is locked: a real account's right password is refused from there...
    assert _login(PORTAL, "erin", PASSWORD, ATTACKER).status_code == 429
    # ...and only from there.
    assert _login(PORTAL, "erin", PASSWORD, ELSEWHERE).logged_in


def test_a_locked_out_attempt_hashes_no_password() -> None:
    """What made a login flood starve the platform was the password hash of every
    attempt (PBKDF2: hundreds of milliseconds of CPU each); once locked out, none."""
    f.user(username="frank")
    _wrong(PORTAL, "frank", ATTACKER, 9)
    assert _login(PORTAL, "frank", "not-the-password", ATTACKER).status_code == 429
    with (
        mock.patch.object(MD5PasswordHasher, "verify", autospec=True) as verify,
        mock.patch.object(MD5PasswordHasher, "encode", autospec=True) as encode,
    ):
        for username in ("frank", "frank", "nobody"):
            assert _login(PORTAL, username, "still-wrong", ATTACKER).status_code == 429
    assert verify.call_count == encode.call_count == 0


def test_the_platforms_own_logins_are_not_counted(client: Client) -> None:
    """A log-in without an HTTP request (a test client's login(), a command) is the
    platform's own code: neither checked nor counted."""
    f.user(username="gina")
    for _ in range(12):
        assert not client.login(username="gina", password="wrong")
    assert client.login(username="gina", password=PASSWORD)
