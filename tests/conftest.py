"""Suite-wide fixtures and the header that says which servers the run used.

``bin/test`` points the suite at the machine's PostgreSQL and Redis when they answer
(DATABASE_URL, REDIS_URL); plain ``pytest`` runs embedded, on SQLite and the
in-memory channel layer. Tests that only mean something on a real server are marked
and skipped, with the reason, on the other.
"""

from __future__ import annotations

from typing import Any

import pytest
from django.conf import settings


def pytest_report_header(config: pytest.Config) -> list[str]:
    db = settings.DATABASES["default"]
    where = (
        f"postgresql {db.get('HOST')}:{db.get('PORT') or 5432}/{db['NAME']}"
        if db["ENGINE"].endswith("postgresql")
        else "sqlite (embedded)"
    )
    layer = settings.CHANNEL_LAYERS["default"]["BACKEND"].rsplit(".", 1)[-1]
    return [
        f"IoUV test services: database={where}; channel layer={layer}; "
        f"celery broker={settings.CELERY_BROKER_URL.split(':', 1)[0]}"
    ]


def on_postgres() -> bool:
    return settings.DATABASES["default"]["ENGINE"].endswith("postgresql")


def on_redis() -> bool:
    return "Redis" in settings.CHANNEL_LAYERS["default"]["BACKEND"]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skip_pg = pytest.mark.skip(reason="needs PostgreSQL (run bin/test with the server up)")
    skip_redis = pytest.mark.skip(reason="needs Redis (run bin/test with the server up)")
    for item in items:
        if "postgres" in item.keywords and not on_postgres():
            item.add_marker(skip_pg)
        if "redis" in item.keywords and not on_redis():
            item.add_marker(skip_redis)


@pytest.fixture(autouse=True)
def _fast_passwords(settings: Any) -> None:
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]
