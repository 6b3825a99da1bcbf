"""The API's interactive documentation (Swagger UI at /api/v1/docs) in a real browser.

The platform runs (iouv.serve) with its production policy; Chromium (Playwright) opens
the page, sees every operation listed, authorizes with an API token and runs "Try it
out" on GET /services. Any CSP violation, and any request leaving the platform's origin
(a CDN, swagger.io's validator), fails the test.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from django.contrib.auth import get_user_model
from playwright.async_api import expect

from accounts.tokens import token_issue
from services.demo import demo_seed
from tests.browser import chromium_browser, needs_chromium
from tests.demo import PASSWORD
from tests.portal import LISTEN_FOR_VIOLATIONS
from tests.servers import db, platform_process

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
    needs_chromium,
]

OPERATIONS = [
    "services_list",
    "session_create",
    "session_read",
    "session_grant",
    "session_end",
    "session_stop",
    "vehicles_list",
]


def _client_token() -> str:
    return token_issue(user=get_user_model().objects.get(username="client"), name="docs")


async def test_the_docs_list_every_operation_and_try_one_out_under_the_policy(
    tmp_path: Path,
) -> None:
    await db(demo_seed, password=PASSWORD, credentials_dir=tmp_path)
    token = await db(_client_token)
    with platform_process() as base:
        async with chromium_browser() as browser:
            context = await browser.new_context()
            await context.add_init_script(script=LISTEN_FOR_VIOLATIONS)
            page = await context.new_page()
            console: list[str] = []
            elsewhere: list[str] = []

            def on_console(message: Any) -> None:
                if "Content Security Policy" in message.text or message.type == "error":
                    console.append(f"{message.type}: {message.text}")

            def on_request(request: Any) -> None:
                if not request.url.startswith((base, "data:")):
                    elsewhere.append(request.url)

            page.on("console", on_console)
            page.on("request", on_request)

            response = await page.goto(f"{base}/api/v1/docs")
            assert response is not None and response.ok
            policy = await response.header_value("content-security-policy")
            assert policy and "script-src 'self'" in policy, policy

            for operation_id in OPERATIONS:
                await expect(page.locator(f"#operations-default-{operation_id}")).to_be_visible()

            # Authorize with the bearer token, as a reader of docs/api.md would.
            await page.click("button.authorize")
            await page.locator(".modal-ux input").fill(token)
            await page.click(".modal-ux button.modal-btn.authorize")
            await page.click(".modal-ux button.btn-done")

            services = page.locator("#operations-default-services_list")
            await services.locator(".opblock-summary").click()
            await services.locator("button.try-out__btn").click()
            await services.locator("button.execute").click()
            status = services.locator(".live-responses-table .response .response-col_status")
            await expect(status.first).to_have_text("200")
            await expect(services.locator(".live-responses-table")).to_contain_text("drive-car")

            violations = await page.evaluate("window.__cspViolations")
            assert violations == [], violations
            assert console == [], console
            assert elsewhere == [], elsewhere
