"""The Content-Security-Policy on every page, and pages that obey it (no inline code).

The policy at work in a real browser is tested in tests/integration/test_csp_browser.py.
"""

from __future__ import annotations

from html.parser import HTMLParser
from typing import Any

import pytest
from django.core.exceptions import ImproperlyConfigured
from django.test import Client
from django.urls import reverse

from iouv.csp_sources import csp_origin_of_template
from services.demo import demo_seed
from tests.deployment import alices_session

PASSWORD = "pw-for-tests"


def policy_of(response: Any) -> dict[str, list[str]]:
    """The response's Content-Security-Policy as {directive: [sources]}."""
    header = response.get("Content-Security-Policy")
    assert header, f"no Content-Security-Policy on {response.status_code} {response}"
    directives = (part.split() for part in header.split(";") if part.strip())
    return {name: sources for name, *sources in directives}


def assert_strict(response: Any) -> None:
    policy = policy_of(response)
    assert policy["default-src"] == ["'self'"]
    assert policy["script-src"] == ["'self'"]
    assert policy["style-src"] == ["'self'"]
    assert policy["object-src"] == ["'none'"] and policy["frame-ancestors"] == ["'none'"]
    # The controller talks to each vehicle's agent directly, on its own host and port.
    assert {"'self'", "ws:", "wss:"} <= set(policy["connect-src"])
    assert "'unsafe-inline'" not in response["Content-Security-Policy"]
    assert "'unsafe-eval'" not in response["Content-Security-Policy"]


class _InlineCode(HTMLParser):
    """Collects what a policy without 'unsafe-inline' would block in a page."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []
        self._in_script = False

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        named = dict(attrs)
        for name, _ in attrs:
            if name == "style" or name.startswith("on"):
                self.found.append(f"<{tag} {name}=...>")
        if tag == "style":
            self.found.append("<style> element")
        # json_script's data blocks are not run, so the policy does not apply to them.
        self._in_script = tag == "script" and not named.get("src")
        if self._in_script and named.get("type") == "application/json":
            self._in_script = False

    def handle_data(self, data: str) -> None:
        if self._in_script and data.strip():
            self.found.append(f"inline <script>: {data.strip()[:60]}")

    def handle_endtag(self, tag: str) -> None:
        if tag == "script":
            self._in_script = False


def inline_code(html: str) -> list[str]:
    parser = _InlineCode()
    parser.feed(html)
    return parser.found


# --- the policy on every page --------------------------------------------------------------


@pytest.fixture
def world() -> None:
    demo_seed(password=PASSWORD)


def _as(username: str) -> Client:
    client = Client()
    assert client.login(username=username, password=PASSWORD)
    return client


@pytest.mark.django_db
@pytest.mark.parametrize(
    ("username", "path"),
    [
        (None, "/accounts/login/"),
        ("client", "/"),
        ("client", "/services/drive-car/"),
        ("client", "/services/rescue-at-sea/"),
        ("client", "/spectate/"),
        ("monitor", "/monitor/"),
        ("admin", "/admin/"),
        ("admin", "/admin/fleet/vehicle/"),
        ("admin", "/admin/fleet/vehicle/add/"),
        ("admin", "/admin/services/service/"),
    ],
)
def test_pages_carry_the_policy_and_hold_no_inline_code(world, username, path) -> None:
    client = _as(username) if username else Client()
    page = client.get(path)
    assert page.status_code == 200
    assert_strict(page)
    assert inline_code(page.content.decode()) == []


@pytest.mark.django_db
def test_the_controller_page_carries_the_policy_and_holds_no_inline_code(client) -> None:
    session, _ = alices_session()
    client.force_login(session.user)
    page = client.get(reverse("session", args=[session.pk]))
    assert page.status_code == 200
    assert_strict(page)
    assert inline_code(page.content.decode()) == []


@pytest.mark.django_db
def test_error_pages_and_json_carry_the_policy(client) -> None:
    assert_strict(client.get("/no-such-page/"))  # 404
    assert_strict(client.get("/api/v1/services"))  # 401, JSON
    assert_strict(client.get("/healthz"))


@pytest.mark.django_db
def test_the_csrf_failure_page_is_the_portals_own_without_inline_style() -> None:
    # Django's built-in page styles itself inline, which the policy blocks.
    page = Client(enforce_csrf_checks=True).post("/accounts/login/", {"username": "x"})
    assert page.status_code == 403
    assert_strict(page)
    assert "CSRF verification failed" in page.content.decode()
    assert inline_code(page.content.decode()) == []


@pytest.mark.parametrize(
    ("url", "source"),
    [
        ("", None),
        ("/tiles/{z}/{x}/{y}.png", None),  # served by the platform: 'self'
        ("https://tile.openstreetmap.org/{z}/{x}/{y}.png", "https://tile.openstreetmap.org"),
        ("https://{s}.tile.example.org/{z}/{x}/{y}.png", "https://*.tile.example.org"),
        ("http://127.0.0.1:8123/{z}/{x}/{y}.png?key=k", "http://127.0.0.1:8123"),
        ("http://user:secret@tiles.local/{z}/{x}/{y}", "http://tiles.local"),
        ("http://[::1]:8080/{z}/{x}/{y}.png", "http://[::1]:8080"),
    ],
)
def test_the_map_tiles_origin_becomes_an_image_source(url, source) -> None:
    assert csp_origin_of_template(url, setting="IOUV_MAP_TILES_URL") == source


@pytest.mark.parametrize(
    "url",
    ["https://tiles.{s}.example.org/{z}.png", "ftp://tiles.example.org/{z}", "https://x:{p}/"],
)
def test_a_tiles_url_with_no_csp_form_is_a_configuration_error(url) -> None:
    with pytest.raises(ImproperlyConfigured, match="IOUV_MAP_TILES_URL"):
        csp_origin_of_template(url, setting="IOUV_MAP_TILES_URL")
