"""The platform's absence is not a vehicle's (fleet.servers): how long a vehicle counts
as silent, given the beats of the platform processes that hold the uplinks."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta

import pytest

from fleet.models import UplinkServer
from fleet.servers import availability, uplink_server_ensure, uplink_server_id, vehicles_silence

pytestmark = pytest.mark.django_db

T0 = datetime(2026, 11, 27, 12, 0, tzinfo=UTC)
A, B = uuid.UUID(int=1), uuid.UUID(int=2)


@pytest.fixture(autouse=True)
def timers(settings):
    settings.IOUV_UPLINK_SERVER_BEAT_S = 1.0
    settings.IOUV_AGENT_RECONNECT_S = 30.0


def s(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def servers(*rows: tuple[uuid.UUID, float, float]) -> None:
    """Uplink servers as (id, started at, last beat), in seconds after T0."""
    for pk, started, alive in rows:
        UplinkServer.objects.create(pk=pk, started_at=s(started), alive_at=s(alive))


def silence(now: float, heard: float | None, server: uuid.UUID | None) -> float | None:
    found = vehicles_silence([("v", None if heard is None else s(heard), server)], s(now))
    return found["v"]


def test_with_its_server_beating_the_silence_is_the_time_since_it_was_heard():
    servers((A, 0, 100))
    assert silence(100, 90, A) == 10
    assert silence(100, None, A) is None


def test_with_no_server_ever_registered_silence_is_judged_as_it_always_was():
    assert silence(100, 40, None) == 60
    assert silence(100, 40, A) == 60


def test_the_silence_stops_counting_when_its_server_stops_beating():
    servers((A, 0, 50))  # killed at 50: nobody beats since
    assert silence(51, 49, A) == 2  # within one beat of its last: still vouched for
    assert silence(60, 49, A) == 2  # the platform gone: nobody could hear the vehicle
    assert silence(600, 49, A) == 2


def test_another_server_there_gives_the_agent_its_reconnect_grace_then_counts():
    servers((A, 0, 50), (B, 0, 200))  # A died at 50, B beat throughout
    assert silence(60, 49, A) == 2  # gone at 51, the grace runs until 81
    assert silence(81, 49, A) == 2
    assert silence(91, 49, A) == 12  # 2 witnessed + 10 past the grace


def test_after_the_whole_platform_was_away_the_grace_counts_from_its_return():
    servers((A, 0, 50), (B, 70, 200))  # nothing between 51 and 70
    assert availability(s(200)).since == s(70)
    assert silence(95, 49, A) == 2  # back at 70, the grace runs until 100
    assert silence(110, 49, A) == 12
    # A vehicle whose server is not known (forgotten) is judged from the return too.
    assert silence(110, 40, uuid.UUID(int=3)) == 10


def test_a_first_server_excuses_nothing_it_could_not_have_heard():
    servers((A, 100, 200))  # the first server ever: the platform had no outage
    assert silence(200, 40, None) == 160


def test_servers_that_overlap_keep_the_platform_available():
    servers((A, 0, 60), (B, 55, 200))  # a rolling restart: B up before A went
    assert availability(s(200)).since == s(0)
    assert availability(s(300)).since == s(300)  # none beats at 300


async def test_a_process_beats_as_an_uplink_server_once_asked():
    server_id = await uplink_server_ensure()
    assert server_id == uplink_server_id()
    row = await UplinkServer.objects.aget(pk=server_id)
    assert row.alive_at >= row.started_at
    assert await uplink_server_ensure() == server_id  # one row, one beat per process
