"""Suite-wide fixtures and the header that says which servers the run used.

``bin/test`` points the suite at the machine's PostgreSQL and Redis when they answer
(DATABASE_URL, REDIS_URL); plain ``pytest`` runs embedded, on SQLite and the
in-memory channel layer. Tests that only mean something on a real server are marked
and skipped, with the reason, on the other.
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import pytest
from django.conf import settings
from django.core.management import call_command
from django.test import override_settings

from tests.browser import chromium_missing_reason
from tests.scheduling import longest_first, measured_density, measured_durations

#: Stacks of a test that runs long (tests/hangs.py).
pytest_plugins = ["tests.hangs", "tests.cpu_report"]


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


#: Each pytest-xdist worker's own ports: worker N takes PORTS_PER_WORKER ports from
#: FIRST_WORKER_PORT + N * PORTS_PER_WORKER (below Linux's ephemeral range, 32768 up, so
#: no outgoing connection holds one); see tests.servers.free_port.
FIRST_WORKER_PORT = 20000
PORTS_PER_WORKER = 500


def pytest_configure(config: pytest.Config) -> None:
    """The test process's own connections without the platform's bound on a silent
    transaction (``DB_IDLE_IN_TRANSACTION_S``): pytest-django runs each test inside one
    transaction that it rolls back at the end, and a test waits on its servers inside
    it for longer than the bound. The platform's processes the tests start keep it
    (tests/services/test_concurrency.py checks it on one)."""
    option = getattr(settings, "DB_IDLE_IN_TRANSACTION_OPTION", "")
    options = settings.DATABASES["default"].get("OPTIONS", {})
    if option and option in options.get("options", ""):
        startup = options["options"].replace(option, "").strip()
        if startup:
            options["options"] = startup
        else:
            del options["options"]


def pytest_xdist_setupnodes(config: pytest.Config, specs: list[Any]) -> None:
    """Isolate the xdist workers from each other before they start, through their
    environment (which the settings read): each its own Redis database (channel layer,
    Celery broker), its own ``IOUV_VAR_DIR`` (logs, mail, the embedded broker's folder)
    and its own range of ports. pytest-django already gives each its own test database
    (``test_<name>_gwN``). Run on the controller, once, with every worker's spec."""
    redis_url = os.environ.get("REDIS_URL", "")
    var_dir = Path(os.environ.get("IOUV_VAR_DIR") or settings.VAR_DIR)
    for index, spec in enumerate(specs):
        env = spec.env
        if redis_url:
            # Database 0 stays the demo's and plain pytest's; Redis has 16 by default.
            env["REDIS_URL"] = _redis_database(redis_url, 1 + index % 15)
        env["IOUV_VAR_DIR"] = str(var_dir / f"worker-{index}")
        first = FIRST_WORKER_PORT + index * PORTS_PER_WORKER
        env["IOUV_TEST_PORTS"] = f"{first}-{first + PORTS_PER_WORKER - 1}"


def _redis_database(url: str, number: int) -> str:
    """``url`` pointing at Redis database ``number`` instead of the one it names."""
    parts = urlsplit(url)
    return urlunsplit(parts._replace(path=f"/{number}"))


def on_postgres() -> bool:
    return settings.DATABASES["default"]["ENGINE"].endswith("postgresql")


def on_redis() -> bool:
    return "Redis" in settings.CHANNEL_LAYERS["default"]["BACKEND"]


#: The slow tiers by where a test lives (a test module may also mark itself): the
#: benchmarks' own machinery on short runs, and what runs real servers, agents and
#: simulators on the wall clock. ``bin/test -m "not browser and not realtime"`` is the
#: quick inner loop; CI runs everything.
TIERS: dict[str, tuple[str, ...]] = {
    "benchmark_harness": ("tests/benchmarks/*",),
    "realtime": (
        "tests/integration/*",
        "kinds/*/tests/test_integration.py",
        "tests/agents/test_mavlink*.py",
        "tests/agents/test_spektrum.py",
        "tests/agents/test_mission*.py",
        "tests/agents/test_shutdown.py",
        "tests/platform/test_worker_outage.py",
        "tests/platform/test_db_pool.py",
        "tests/platform/test_worker_connections.py",
    ),
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    skip_pg = pytest.mark.skip(reason="needs PostgreSQL (run bin/test with the server up)")
    skip_redis = pytest.mark.skip(reason="needs Redis (run bin/test with the server up)")
    chromium = chromium_missing_reason()
    skip_browser = pytest.mark.skip(reason=chromium or "")
    for item in items:
        where = item.nodeid.split("::", 1)[0]
        for marker, patterns in TIERS.items():
            if any(fnmatch.fnmatch(where, pattern) for pattern in patterns):
                item.add_marker(marker)
        if "browser" in item.keywords and chromium is not None:
            item.add_marker(skip_browser)
        if "postgres" in item.keywords and not on_postgres():
            item.add_marker(skip_pg)
        if "redis" in item.keywords and not on_redis():
            item.add_marker(skip_redis)
    # Under pytest-xdist (each worker collects, in the same order): the slow modules
    # spread over the workers' first slices, longest first, the CPU's busiest apart
    # (tests/scheduling.py).
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    items[:] = longest_first(items, workers, measured_durations(), measured_density())


@pytest.fixture(scope="module")
def module_database(django_db_setup: Any, django_db_blocker: Any) -> Iterator[None]:
    """The test database, open to the module for its whole run: what its tests write is
    committed, as ``transaction=True`` would (the servers and consumer threads they
    start see it), and the database is emptied once, after the module, as a
    transactional test's teardown does after each test (some 2 s of it: TRUNCATE of
    every table, then post_migrate's permissions and roles). For a world the tests
    share (started once: the slow part; it depends on this, so it stops first), or
    for tests that each write rows of their own and look only at those.

    A module using it marks its tests ``django_db`` (a world's), or not at all; not
    ``transaction=True``, which would empty the database after each test."""
    with django_db_blocker.unblock():
        # The demo users' passwords hashed the fast way (the platform the tests start
        # accepts it), as _fast_passwords does for each test.
        with override_settings(PASSWORD_HASHERS=["django.contrib.auth.hashers.MD5PasswordHasher"]):
            yield
        call_command("flush", interactive=False, verbosity=0)


@pytest.fixture(autouse=True)
def _fast_passwords(settings: Any) -> None:
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]


class AgentInbox:
    """What the platform owes one vehicle's agent, read as the outbox delivers it.

    ``take(n)`` puts the next ``n`` owed messages on the (imaginary) uplink, as
    fleet.outbox does (they count as sent from then on), and returns them without their
    ``id``, oldest first; fewer than ``n`` owed is a test failure. ``ack(message)``
    answers as the agent does, through the uplink's own code path.
    """

    def __init__(self, vehicle: Any) -> None:
        self.vehicle = vehicle
        self._keys: dict[int, str] = {}
        self._last: list[Any] = []

    def owed(self) -> list[Any]:
        from fleet.models import AgentMessage

        return list(
            AgentMessage.objects.filter(vehicle_id=self.vehicle.pk, state="pending")
            .exclude(kind="disconnect")
            .order_by("id")
        )

    def take(self, n: int = 1) -> list[dict[str, Any]]:
        from django.db.models import F
        from django.utils import timezone

        from fleet.models import AgentMessage

        rows = [r for r in self.owed() if r.pk not in self._keys][:n]
        assert len(rows) == n, f"the agent is owed {len(rows)} new message(s), not {n}"
        AgentMessage.objects.filter(pk__in=[r.pk for r in rows]).update(
            attempts=F("attempts") + 1, sent_at=timezone.now()
        )
        messages = []
        for row in rows:
            self._keys[row.pk] = str(row.key)
            messages.append(dict(row.message))
        self._last = rows
        return messages

    def ids(self) -> list[str]:
        """The ``id`` each message of the last ``take`` carried on the uplink."""
        return [str(row.key) for row in self._last]

    def ack(self, message: dict[str, Any] | None = None, *, ok: bool = True) -> None:
        """Acknowledge ``message`` (one returned by ``take``), or every message taken."""
        from agents.protocol.messages import Ack
        from fleet.models import AgentMessage
        from fleet.uplink import _acked

        rows = AgentMessage.objects.filter(pk__in=list(self._keys)).order_by("id")
        for row in rows:
            if message is None or row.message == message:
                _acked(vehicle_id=str(self.vehicle.pk), ack=Ack(id=self._keys[row.pk], ok=ok))


@pytest.fixture
def inbox() -> Any:
    """``inbox(vehicle)``: an :class:`AgentInbox` for that vehicle's agent, whose
    ``take`` is also returned by calling it the old way (``take = inbox(v); take()``)."""

    def listen(vehicle: Any) -> Any:
        box = AgentInbox(vehicle)

        def take(n: int = 1) -> list[dict[str, Any]]:
            return box.take(n)

        take.box = box  # type: ignore[attr-defined]
        take.ack = box.ack  # type: ignore[attr-defined]
        take.owed = box.owed  # type: ignore[attr-defined]
        take.ids = box.ids  # type: ignore[attr-defined]
        return take

    return listen
