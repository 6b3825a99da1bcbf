"""Headless Chromium for browser tests: Debian's ``chromium-headless-shell`` driven by
Playwright.

Playwright's own browser download does not work on the test machines, so tests drive
the distribution's build (``bin/install-chromium`` installs it; ``bin/test`` calls that
first). It is the headless shell, as Playwright's own headless runs are: Chromium's
rendering, media and WebRTC without the desktop browser around them. The full
``chromium`` in headless mode passes the same tests, but the shell costs the machine
about a fifth less CPU over the browser tests (78 against 100 CPU-s for test_portal and
test_controller_paths_browser), and a saturated suite is bound by CPU.

Test modules import from here; this is not a conftest::

    from tests.browser import chromium_browser, needs_chromium

    @needs_chromium
    async def test_page() -> None:
        async with chromium_browser(webrtc_loopback=True) as browser:
            page = await browser.new_page()
            ...

Tests run in pytest-asyncio's event loop, so this uses Playwright's *async* API (the
sync API, and pytest-playwright's ``page`` fixture, refuse to run inside a running
loop). For a sync suite using pytest-playwright, return :func:`launch_options` from a
``browser_type_launch_args`` fixture in conftest.py.

Without Chromium (or without the ``playwright`` package) the tests are skipped with a
reason saying how to get it, never failed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import AsyncIterator, Sequence
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from playwright.async_api import Browser

#: The Chromium binary; IOUV_CHROMIUM overrides (e.g. ``/usr/bin/chromium``, or a Chrome
#: elsewhere).
CHROMIUM_PATH = os.environ.get("IOUV_CHROMIUM", "/usr/bin/chromium-headless-shell")

#: Flags that keep Chromium quiet and self-contained on a closed network. Playwright
#: adds ``--headless`` itself (``headless=True``).
CHROMIUM_ARGS: list[str] = [
    "--no-sandbox",  # tests run as root in containers, where the sandbox cannot start
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--autoplay-policy=no-user-gesture-required",  # <video> plays without a click
]

#: Extra flags for WebRTC between the page and a peer on 127.0.0.1 only: let Chromium
#: gather loopback candidates, and give real addresses rather than mDNS ``.local`` names
#: (which aioice cannot resolve without multicast). The aiortc side must offer
#: 127.0.0.1 too (``VideoService(ice_host_addresses=["127.0.0.1"])``).
WEBRTC_LOOPBACK_ARGS: list[str] = [
    "--allow-loopback-in-peer-connection",
    "--disable-features=WebRtcHideLocalIpsWithMdns",
]


def chromium_missing_reason() -> str | None:
    """Why browser tests cannot run here, or None when they can."""
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "needs the 'playwright' package (pip install -e '.[dev]')"
    if not (os.access(CHROMIUM_PATH, os.X_OK) or shutil.which(CHROMIUM_PATH)):
        return f"needs Chromium at {CHROMIUM_PATH} (run bin/install-chromium as root)"
    return None


#: Marks a browser test (the ``browser`` tier: ``bin/test -m "not browser"`` leaves them
#: out); the suite's conftest skips them, with the reason, when Chromium is unavailable.
needs_chromium = pytest.mark.browser


def launch_options(
    *, webrtc_loopback: bool = False, extra_args: Sequence[str] = ()
) -> dict[str, Any]:
    """Keyword arguments for ``browser_type.launch()`` (or pytest-playwright's
    ``browser_type_launch_args`` fixture)."""
    args = [*CHROMIUM_ARGS, *(WEBRTC_LOOPBACK_ARGS if webrtc_loopback else ()), *extra_args]
    return {"executable_path": CHROMIUM_PATH, "headless": True, "args": args}


@contextlib.asynccontextmanager
async def chromium_browser(
    *, webrtc_loopback: bool = False, extra_args: Sequence[str] = ()
) -> AsyncIterator[Browser]:
    """A headless Chromium, closed (with Playwright's driver) when the block exits.

    Skips the calling test when Chromium is missing. ``webrtc_loopback`` adds
    :data:`WEBRTC_LOOPBACK_ARGS`.
    """
    reason = chromium_missing_reason()
    if reason is not None:
        pytest.skip(reason)
    from playwright.async_api import async_playwright

    async with async_playwright() as pw:
        browser = await pw.chromium.launch(
            **launch_options(webrtc_loopback=webrtc_loopback, extra_args=extra_args)
        )
        try:
            yield browser
        finally:
            await browser.close()
