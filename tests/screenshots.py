"""Screenshots of the portal's pages, at a desktop's and a phone's viewport.

    python -m tests.screenshots --out docs/screenshots     (or bin/screenshots)

Starts what the browser tests start (tests/tour.py: the seeded demo, the platform, a
Celery worker, the simulated car, drone, search and lifeguard drones, Chromium) on a
database of its own, made for the run and dropped after it (``<NAME>_screenshots`` on
the server of DATABASE_URL, which must be PostgreSQL; REDIS_URL must be set), then
opens each page of the tour in its real state (video playing, telemetry in, the
mission map drawn) and saves ``<page>-desktop.png`` and ``<page>-phone.png``.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
from pathlib import Path

#: The order of the tour: the monitor last, so that it lists the sessions the tour
#: started; the rescue request form before the mission it would start.
ORDER = (
    "catalog",
    "car-controller",
    "drone-controller",
    "rescue-request",
    "rescue-mission",
    "monitor",
)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m tests.screenshots", description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("docs/screenshots"), help="folder")
    parser.add_argument("--pages", nargs="+", choices=ORDER, default=list(ORDER))
    parser.add_argument(
        "--full-page",
        action="store_true",
        help="the whole page, not only what the viewport shows (the default: what fits "
        "the screen is what the layout is judged by)",
    )
    return parser.parse_args(argv)


async def take(args: argparse.Namespace, directory: Path) -> list[Path]:
    """Run the tour's world and save the screenshots; returns the files written."""
    from playwright.async_api import Page

    from tests.tour import VIEWPORTS, open_page, tour_world

    args.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    async with tour_world(directory) as tour:
        # Pages stay open until the end: closing a controller's page is a lost link,
        # and the vehicle's fail-safe would show on the pages after it.
        opened: list[Page] = []
        try:
            for name in [p for p in ORDER if p in args.pages]:
                for viewport in VIEWPORTS:
                    page = await open_page(tour, name, viewport)
                    opened.append(page)
                    # From the top, as the page opens (a click on the way, such as
                    # "Take control", may have scrolled it).
                    await page.evaluate("() => window.scrollTo(0, 0)")
                    path = args.out / f"{name}-{viewport}.png"
                    await page.screenshot(path=str(path), full_page=args.full_page)
                    written.append(path)
                    print(f"wrote {path}", flush=True)
        finally:
            for page in opened:
                await page.context.close()
    return written


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "iouv.settings")
    import django

    django.setup()
    from django.conf import settings
    from django.db import connection

    from tests.browser import chromium_missing_reason

    if reason := chromium_missing_reason():
        print(f"screenshots: {reason}", file=sys.stderr)
        return 2
    if connection.vendor != "postgresql" or not settings.REDIS_URL:
        print(
            "screenshots: needs DATABASE_URL (PostgreSQL) and REDIS_URL: the platform, its "
            "worker and the page tour share them, as in the integration tests",
            file=sys.stderr,
        )
        return 2
    # A database of the run's own, as the tests have: the demo is seeded afresh, and no
    # one's data (nor a test run's database) is touched.
    name = settings.DATABASES["default"]["NAME"]
    settings.DATABASES["default"]["TEST"]["NAME"] = f"{name}_screenshots"
    connection.creation.create_test_db(verbosity=0, autoclobber=True, serialize=False)
    try:
        with tempfile.TemporaryDirectory(prefix="iouv-screenshots-") as directory:
            asyncio.run(take(args, Path(directory)))
    finally:
        connection.close()
        connection.creation.destroy_test_db(name, verbosity=0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
