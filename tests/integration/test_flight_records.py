"""Flight records end to end (docs/records.md): the platform (iouv.serve, Postgres, Redis)
and a simulated MAVLink quadcopter's agent; a user flies it while the platform is killed
and started again; the record reaches the platform whole and is exported.

What a reader of the exports sees is checked with independent readers: gpxpy for the
GPX, ElementTree for the KML, pymavlink's own log reader for the ``.tlog``.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import itertools
import json
import time
import zipfile
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import gpxpy
import pytest
from django.test import Client
from playwright.async_api import expect
from websockets.asyncio.client import connect

from accounts.roles import MONITOR
from agents.config import AgentConfig, ControlConfig, RecordsConfig
from agents.protocol import PROTOCOL_VERSION
from agents.protocol.messages import Ack, Record
from agents.protocol.messages import RecordSample as Sample
from agents.runtime import Agent
from agents.vehicles.mavlink.dialect import mavutil
from fleet.credentials import vehicle_issue_credential
from fleet.models import Vehicle
from services.models import RecordBatch, RecordSample, Service, Session
from services.records.keeping import record_batch_store, record_verify
from services.sessions.ending import session_end
from services.sessions.signing import platform_public_key_pem
from tests import factories as f
from tests.browser import chromium_browser, needs_chromium
from tests.control import command, recv
from tests.deployment import TARGET, limited_service, registered_vehicle, session_requested
from tests.portal import sign_in
from tests.servers import PlatformServer, agent_configured, db, platform_server, until
from tests.vehicles import QUADCOPTER, agent_registered, session_deployed, vehicle_served

pytestmark = [
    pytest.mark.postgres,
    pytest.mark.redis,
    pytest.mark.django_db(transaction=True),
]
COMMANDS = ["arm", "take_off", "front", "land"]
KML = "{http://www.opengis.net/kml/2.2}"
GX = "{http://www.google.com/kml/ext/2.2}"


@pytest.fixture
async def flight(
    tmp_path: Path,
) -> AsyncIterator[tuple[PlatformServer, Agent, Vehicle, Service]]:
    quad, credential, service = await db(
        vehicle_served,
        "quad-rec",
        QUADCOPTER,
        service="fly-recorded",
        commands=COMMANDS,
        failsafe_action="land",
        link_loss_timeout_ms=3000,
        attributes={"features": ["gps"]},
        max_altitude_m=30,
    )
    with platform_server() as platform:
        config = AgentConfig(
            platform_url=platform.base.replace("http", "ws"),
            vehicle_id=str(quad.pk),
            credential=credential,
            platform_public_key=await db(platform_public_key_pem),
            adapter="mavlink",
            adapter_options={
                "origin": [f.HOME[0], f.HOME[1]],
                "simulator": {"speedup": 4},
            },
            control=ControlConfig(host="127.0.0.1", port=0),
            name=quad.name,
            # Back quickly after the platform's restart.
            reconnect_max_s=1.0,
            records=RecordsConfig(directory=tmp_path / "records"),
        )
        async with agent_configured(config) as (agent, _):
            yield platform, agent, quad, service


async def _fly_through_an_outage(
    platform: PlatformServer, agent: Agent, url: str, grant: str, *, outage_s: float = 6
) -> None:
    """Take off, fly forward, lose the platform for ``outage_s`` while flying (forward
    for its first 6 s, then hovering: the user keeps the link alive), land."""
    async with connect(url, proxy=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "auth", "grant": grant}))
        assert (await recv(ws, "welcome"))["role"] == "controller"
        assert (await command(ws, 1, "take_off", altitude_m=5))["ok"]
        drone: Any = agent.adapter
        deadline = time.monotonic() + 15
        while (drone.t.alt or 0) < 4.5:
            assert time.monotonic() < deadline, "the drone did not climb"
            await ws.send(json.dumps({"type": "keepalive"}))
            await asyncio.sleep(0.2)
        seq = 2
        await asyncio.to_thread(platform.kill)
        killed = time.monotonic()
        while time.monotonic() - killed < outage_s:  # flying while the platform is away
            if time.monotonic() - killed < 6:
                assert (await command(ws, seq, "front", speed_mps=3))["ok"]
                seq += 1
                await asyncio.sleep(0.2)
            else:
                await ws.send(json.dumps({"type": "keepalive"}))
                # Read what the agent says meanwhile (pings, events): a client that
                # stops reading stops answering its socket's pings and is cut off.
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ws.recv(), 0.2)
        assert agent.recorder.pending, "batches wait on the vehicle meanwhile"
        # The user keeps the link alive while the platform starts (tens of seconds on a
        # saturated machine): keepalives out, and reading, as the page does.
        starting = asyncio.create_task(asyncio.to_thread(platform.start))
        while not starting.done():
            await ws.send(json.dumps({"type": "keepalive"}))
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(ws.recv(), 0.2)
        await starting
        # A refused command is recorded with its acknowledgement too.
        refused = await command(ws, seq, "take_off", altitude_m=500)
        assert not refused["ok"]
        assert (await command(ws, seq + 1, "land"))["ok"]
        while drone.t.armed:
            await ws.send(json.dumps({"type": "keepalive"}))
            await asyncio.sleep(0.2)
            assert time.monotonic() - killed < outage_s + 34, "the drone did not land"


async def _all_uploaded(
    agent: Agent, session: Session, *, ended: bool = False
) -> list[RecordSample]:
    """The session's samples once every one written has reached the platform; with
    ``ended``, the vehicle stops recording the session first (as the task's end makes
    it), so that nothing is added after: what the exports hold is then exactly that."""
    recording = agent.recorder.session
    if ended:
        agent.recorder.session_end()
    else:
        agent.recorder.flush()
    written = recording.next_seq - 1 if recording else 0

    async def stored() -> bool:
        count = await db(RecordSample.objects.filter(session_id=session.pk).count)
        return not agent.recorder.pending and count >= written

    await until(stored, within=20, what="every batch to reach the platform")
    return await db(
        lambda: list(RecordSample.objects.filter(session_id=session.pk).order_by("seq"))
    )


def _another_vehicle(quad: Vehicle) -> tuple[Vehicle, str]:
    other = f.vehicle(station=f.station(), vtype=quad.vehicle_type, name="quad-other", online=False)
    return other, vehicle_issue_credential(vehicle=other)


def _utc(t: float) -> datetime:
    ms = round(t * 1000)
    return datetime.fromtimestamp(ms // 1000, tz=UTC).replace(microsecond=ms % 1000 * 1000)


def _get(user: Any, path: str) -> Any:
    client = Client()
    if user is not None:
        client.force_login(user)
    return client.get(path)


async def test_a_flight_through_a_platform_outage_is_recorded_whole_and_exported(flight, tmp_path):
    platform, agent, quad, service = flight
    await agent_registered(quad, within=20, positioned=True)
    session, user_task = await session_deployed(agent, service)
    await _fly_through_an_outage(platform, agent, user_task.control_url, user_task.grant)
    samples = await _all_uploaded(agent, session, ended=True)

    # Nothing lost: contiguous numbers, each batch stored once, the record checks out.
    assert [s.seq for s in samples] == list(range(1, len(samples) + 1))
    kinds = {s.kind for s in samples}
    assert {"telemetry", "command", "event", "tlog"} <= kinds
    commands = [s.data for s in samples if s.kind == "command"]
    assert [c["name"] for c in commands if c["source"] == "user"][:2] == ["take_off", "front"]
    assert any(not c["ok"] and c["code"] for c in commands if c["source"] == "user")
    track = [s for s in samples if s.kind == "telemetry" and s.data["lat"] is not None]
    moving = [s for s in track if s.data["armed"]]
    span = moving[-1].t - moving[0].t
    assert len(moving) >= 2 * span, "at least 2 Hz while flying"
    check = await db(record_verify, session=session)
    assert check.ok, check.problems

    # The exports, as the session's user downloads them.
    owner = await db(lambda: Session.objects.get(pk=session.pk).user)
    base = f"/sessions/{session.pk}/record/"

    gpx_answer = await db(_get, owner, base + "gpx")
    assert gpx_answer.status_code == 200
    gpx = gpxpy.parse(gpx_answer.content.decode())
    # Named as the replay names the vehicle, with the id the CSVs' column holds.
    assert [t.name for t in gpx.tracks] == [f"{quad.name} (vehicle {quad.pk})"]
    points = [p for t in gpx.tracks for seg in t.segments for p in seg.points]
    assert [(p.latitude, p.longitude, p.elevation) for p in points] == [
        (s.data["lat"], s.data["lon"], s.data["alt"]) for s in track
    ]
    assert [p.time for p in points] == [_utc(s.t) for s in track]

    kml = ET.fromstring((await db(_get, owner, base + "kml")).content)
    assert [p.findtext(f"{KML}name") for p in kml.iter(f"{KML}Placemark")] == [
        f"{quad.name} (vehicle {quad.pk})"
    ]
    coords = [c.text.split() for c in kml.iter(f"{GX}coord")]
    assert [(float(lon), float(lat), float(alt)) for lon, lat, alt in coords] == [
        (s.data["lon"], s.data["lat"], s.data["alt"]) for s in track
    ]
    assert len(list(kml.iter(f"{KML}when"))) == len(track)

    # pymavlink reads the .tlog: the positions the track holds are the ones it says.
    tlog = (await db(_get, owner, base + "tlog")).content
    tlog_path = tmp_path / "export.tlog"
    await asyncio.to_thread(tlog_path.write_bytes, tlog)
    reader = mavutil.mavlink_connection(str(tlog_path))
    positions = set()
    times = []
    while (msg := reader.recv_match(type="GLOBAL_POSITION_INT")) is not None:
        positions.add((msg.lat / 1e7, msg.lon / 1e7))
        times.append(msg._timestamp)
    assert positions
    # The track's samples while the tlog runs (a batch can carry telemetry whose
    # MAVLink message rides in the next batch's tlog piece).
    logged = [s for s in track if times[0] + 0.5 < s.t <= times[-1]]
    assert len(logged) > len(track) / 2
    assert all((s.data["lat"], s.data["lon"]) in positions for s in logged)
    # It holds what the agent sent the autopilot too, as a ground station's .tlog does:
    # the take-off's COMMAND_LONG and the "front" setpoints, from the agent's system id.
    reader = mavutil.mavlink_connection(str(tlog_path))
    sent = set()
    while msg := reader.recv_match(type=["COMMAND_LONG", "SET_POSITION_TARGET_LOCAL_NED"]):
        sent.add((msg.get_type(), msg.get_srcSystem()))
    agent_system = agent.adapter.link.config.source_system
    assert {("COMMAND_LONG", agent_system), ("SET_POSITION_TARGET_LOCAL_NED", agent_system)} <= sent

    # Streamed (it may hold hours of video): read to its end.
    archive = zipfile.ZipFile(io.BytesIO((await db(_get, owner, base + "zip")).getvalue()))
    assert {"track.gpx", "track.kml", "track.csv", "commands.csv", "flight.tlog"} <= set(
        archive.namelist()
    )
    assert json.loads(archive.read("verification.json"))["ok"] is True
    chain = json.loads(archive.read("log.json"))
    batches = await db(RecordBatch.objects.filter(session_id=session.pk).count)
    assert sum(e["kind"] == "record_batch" for e in chain) == batches
    assert archive.read("commands.csv").decode().count("\n") == len(commands) + 1
    manifest = json.loads(archive.read("manifest.json"))
    assert {e["name"] for e in manifest["files"]} == set(archive.namelist()) - {"manifest.json"}
    assert manifest["video"]["recorded"] is False  # this platform runs no SFU

    # Who may open it: the user and monitors; another client is told nothing exists.
    stranger = await db(f.user, "mallory")
    monitor = await db(f.user, "mona", roles=(MONITOR,))
    assert (await db(_get, stranger, base)).status_code == 404
    assert (await db(_get, stranger, base + "zip")).status_code == 404
    assert (await db(_get, None, base + "gpx")).status_code == 302  # to the login page
    summary = await db(_get, monitor, base)
    assert summary.status_code == 200 and summary.json()["verification"]["ok"]

    # One sample changed in the database: the record no longer checks out.
    await db(
        lambda: RecordSample.objects.filter(pk=track[3].pk).update(
            data={**track[3].data, "lat": track[3].data["lat"] + 0.001}
        )
    )
    tampered = await db(record_verify, session=session)
    assert not tampered.ok
    assert any("does not match its digest" in p for p in tampered.problems)


async def test_bad_record_frames_are_refused_and_a_batch_sent_twice_is_stored_once(flight):
    platform, agent, quad, service = flight
    await agent_registered(quad, within=20, positioned=True)
    session, _ = await session_deployed(agent, service)
    other, credential = await db(_another_vehicle, quad)
    stored_before = await db(RecordSample.objects.filter(session_id=session.pk).count)
    uplink = platform.base.replace("http", "ws") + "/ws/agent/"
    async with connect(uplink, proxy=None, compression=None, max_size=None) as ws:
        await ws.send(
            json.dumps(
                {
                    "type": "hello",
                    "v": PROTOCOL_VERSION,
                    "vehicle_id": str(other.pk),
                    "credential": credential,
                }
            )
        )
        assert json.loads(await ws.recv())["type"] == "welcome"

        def batch(first: int, seqs: list[int], session_id: str = str(session.pk)) -> str:
            return json.dumps(
                {
                    "type": "record",
                    "id": f"record:{session_id}:{first}",
                    "session_id": session_id,
                    "first": first,
                    "samples": [
                        {"seq": n, "t": 1.8e9, "kind": "telemetry", "data": {"lat": 1.0}}
                        for n in seqs
                    ],
                }
            )

        async def answer() -> dict[str, Any]:
            while True:
                msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                if msg["type"] in ("error", "ack"):
                    return msg

        await ws.send(batch(1, [1, 3]))  # a gap
        refused = await answer()
        assert refused["type"] == "error" and refused["code"] == "bad_field"
        assert "samples[1].seq" in refused["message"]
        await ws.send(batch(1, [1])[:-1] + ', "pad": "' + "x" * 70_000 + '"}')  # too big
        assert (await answer())["code"] == "too_large"
        # Another vehicle's session: refused for good, by its id.
        await ws.send(batch(1, [1]))
        assert await answer() == {
            "type": "ack",
            "id": f"record:{session.pk}:1",
            "ok": False,
            "detail": "not a session of this vehicle",
        }
    # The flight's own record is untouched by all that.
    samples = await _all_uploaded(agent, session)
    assert not any(s.t == 1.8e9 for s in samples)
    assert [s.seq for s in samples] == list(range(1, len(samples) + 1))
    assert stored_before <= len(samples)

    # Its first batch sent again: acknowledged again, stored once, chained once.
    acks: list[Ack] = []
    keep = agent.recorder.acked

    def acked(ack: Ack) -> bool:
        acks.append(ack)
        return keep(ack)

    agent.recorder.acked = acked
    first = await db(lambda: RecordBatch.objects.filter(session_id=session.pk).order_by("first")[0])
    rows = await db(lambda: list(first.samples.order_by("seq")))
    again = Record(
        id=f"record:{session.pk}:{first.first}",
        session_id=str(session.pk),
        first=first.first,
        samples=[Sample(seq=r.seq, t=r.t, kind=r.kind, data=r.data) for r in rows],
    )
    events_before = await db(
        lambda: Session.objects.get(pk=session.pk).events.filter(kind="record_batch").count()
    )
    agent.uplink.send(again)

    async def answered() -> bool:
        return any(a.id == again.id for a in acks)

    await until(answered, within=10, what="the platform to acknowledge the repeated batch")
    [repeat] = [a for a in acks if a.id == again.id]
    assert repeat.ok and repeat.detail == "already stored"
    assert await db(RecordBatch.objects.filter(session_id=session.pk, first=1).count) == 1
    chained = await db(
        lambda: (
            Session.objects.get(pk=session.pk)
            .events.filter(kind="record_batch", data__first=1)
            .count()
        )
    )
    assert chained == 1
    assert events_before >= 1
    assert (await db(record_verify, session=session)).ok


async def _fly_a_hop(agent: Agent, url: str, grant: str) -> None:
    """Take off, fly forward for a few seconds, land and wait until disarmed."""
    async with connect(url, proxy=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "auth", "grant": grant}))
        assert (await recv(ws, "welcome"))["role"] == "controller"
        assert (await command(ws, 1, "take_off", altitude_m=5))["ok"]
        drone: Any = agent.adapter

        async def climbed() -> bool:
            await ws.send(json.dumps({"type": "keepalive"}))
            return (drone.t.alt or 0) >= 4.5

        await until(climbed, within=20, what="the drone to climb")
        for seq in range(2, 12):
            assert (await command(ws, seq, "front", speed_mps=3))["ok"]
        assert (await command(ws, 12, "land"))["ok"]

        async def landed() -> bool:
            await ws.send(json.dumps({"type": "keepalive"}))
            return not drone.t.armed

        await until(landed, within=40, what="the drone to land")


@needs_chromium
async def test_a_live_sessions_replay_follows_the_drone_and_scrubs_back_while_it_flies(flight):
    """The replay of a session still flying: left at its end, the slider follows the
    drone as its samples arrive; moved back, it stays where it was put while more
    arrive, the marker on that earlier position."""
    platform, agent, quad, service = flight
    await agent_registered(quad, within=20, positioned=True)
    session, user_task = await session_deployed(agent, service)
    owner = await db(lambda: Session.objects.get(pk=session.pk).user)
    seq = itertools.count(1)
    # The browser starts first: the agent closes a channel not authenticated within
    # 5 s, and a loaded machine takes longer than that to start Chromium.
    async with (
        chromium_browser() as browser,
        connect(user_task.control_url, proxy=None, compression=None) as ws,
    ):
        await ws.send(json.dumps({"type": "auth", "grant": user_task.grant}))
        assert (await recv(ws, "welcome"))["role"] == "controller"
        assert (await command(ws, next(seq), "take_off", altitude_m=5))["ok"]
        page = await browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))

        async def flying_until(condition: str, what: str) -> None:
            """Fly forward (each command answered: the link stays alive) until the
            page's ``condition`` holds."""
            deadline = time.monotonic() + 60
            while not await page.evaluate(condition):
                assert time.monotonic() < deadline, f"not seen in 60 s: {what}"
                await command(ws, next(seq), "front", speed_mps=2)
                await asyncio.sleep(0.2)

        await sign_in(page, platform.base, owner.username, password="pw-for-tests")
        await page.goto(f"{platform.base}/sessions/{session.pk}/replay/")
        await expect(page.locator("#replay")).to_have_attribute("data-loaded", "true")
        await expect(page.locator("[data-replay-status]")).to_contain_text("Live")
        await flying_until("() => window.IoUVReplay.times().length >= 5", "five positions")
        # Left at its end, the slider follows the drone.
        slider = page.locator("[data-replay-slider]")
        await slider.fill(await slider.get_attribute("max") or "0")
        seen = await page.evaluate("() => window.IoUVReplay.times().length")
        await flying_until(
            f"() => window.IoUVReplay.times().length > {seen} + 5", "more positions, live"
        )
        latest = "() => { const t = window.IoUVReplay.times();"
        latest += " return window.IoUVReplay.current().t === t[t.length - 1]; }"
        assert await page.evaluate(latest), "the slider stayed behind at the end"
        # Scrubbed back, it stays on that position while the drone flies on.
        await slider.fill("2")
        seen = await page.evaluate("() => window.IoUVReplay.times().length")
        await flying_until(
            f"() => window.IoUVReplay.times().length > {seen} + 5", "more positions, live"
        )
        current = await page.evaluate("() => window.IoUVReplay.current()")
        assert current["t"] == (await page.evaluate("() => window.IoUVReplay.times()"))[2]
        assert await page.evaluate("() => window.IoUVReplay.markerLatLng()") == [
            current["data"]["lat"],
            current["data"]["lon"],
        ]
        assert await slider.input_value() == "2"
        assert not errors, errors
        assert (await command(ws, next(seq), "land"))["ok"]


@needs_chromium
async def test_the_replay_page_moves_the_marker_and_gauges_with_its_slider(flight):
    platform, agent, quad, service = flight
    await agent_registered(quad, within=20, positioned=True)
    session, user_task = await session_deployed(agent, service)
    await _fly_a_hop(agent, user_task.control_url, user_task.grant)
    samples = await _all_uploaded(agent, session, ended=True)
    track = [s for s in samples if s.kind == "telemetry" and s.data["lat"] is not None]
    commands = [s.data for s in samples if s.kind == "command"]
    owner = await db(lambda: Session.objects.get(pk=session.pk).user)

    async with chromium_browser() as browser:
        page = await browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        await sign_in(page, platform.base, owner.username, password="pw-for-tests")
        await page.goto(f"{platform.base}/sessions/{session.pk}/replay/")
        await expect(page.locator("#replay")).to_have_attribute("data-loaded", "true")
        await expect(page.locator("[data-replay-no-video]")).to_have_text(
            "No video was recorded for this session."
        )
        # The marker starts at the track's first point.
        first = track[0].data
        assert await page.evaluate("() => window.IoUVReplay.markerLatLng()") == [
            first["lat"],
            first["lon"],
        ]
        # The slider moved to a sample in flight: the marker and gauges are that sample's.
        index = max(i for i, s in enumerate(track) if s.data["armed"] and s.data["alt"] > 3)
        sample = track[index].data
        await page.locator("[data-replay-slider]").fill(str(index))
        assert await page.evaluate("() => window.IoUVReplay.markerLatLng()") == [
            sample["lat"],
            sample["lon"],
        ]

        # Rounded as the page rounds (toFixed), which differs from Python's at a tie.
        def fixed(value: float) -> Any:
            return page.evaluate("v => v.toFixed(1)", value)

        await expect(page.locator('[data-gauge="alt"]')).to_have_text(
            f"{await fixed(sample['alt'])} m"
        )
        speed = "\N{EN DASH}" if sample["speed"] is None else f"{await fixed(sample['speed'])} m/s"
        await expect(page.locator('[data-gauge="speed"]')).to_have_text(speed)
        await expect(page.locator('[data-gauge="mode"]')).to_have_text(sample["mode"])
        # The timeline says who sent each command, what it was and how it was answered.
        items = page.locator('[data-replay-timeline] li[data-kind="command"]')
        await expect(items).to_have_count(len(commands))
        texts = await items.all_text_contents()
        assert "user · take_off · ok" in texts[0]
        assert any("user · front · ok" in t for t in texts)
        assert not errors

        # Another user is told there is no such session.
        stranger = await db(f.user, "mallory")
        other = await browser.new_page()
        await sign_in(other, platform.base, stranger.username, password="pw-for-tests")
        answer = await other.goto(f"{platform.base}/sessions/{session.pk}/replay/")
        assert answer is not None and answer.status == 404


#: The rescue replayed below: when its record starts, and each vehicle's positions
#: (lat, lon, alt) at its own instants from then (s): the drone searches northward
#: from the start, the boat sets out eastward once the drone has found the person.
RESCUE_T0 = 1.8e9
RESCUE = {
    "rescue-drone": [(float(i), (40.6310 + i * 0.0005, -8.6590, 20.0 + i)) for i in range(10)],
    "rescue-boat": [(4.5 + i, (40.6290, -8.6560 + i * 0.0005, 0.0)) for i in range(6)],
}


def _rescue_recorded() -> Session:
    """An ended rescue session whose two vehicles each uploaded their record: their
    positions (:data:`RESCUE`), the drone's take-off and its finding, the boat's order
    to go. The boat's batch is stored first, though its samples are the later."""
    vehicles = {name: registered_vehicle(name=name) for name in RESCUE}
    service = limited_service(roles=[{"name": "search"}, {"name": "delivery"}])
    user = f.user(username="rita")
    session = session_requested(user=user, service=service, target=TARGET).session
    others = {
        "rescue-drone": [
            (0.5, "command", {"source": "user", "name": "take_off", "ok": True}),
            (5.2, "event", {"event": "person_found"}),
        ],
        "rescue-boat": [(6.2, "command", {"source": "user", "name": "go_to", "ok": True})],
    }
    for name in ("rescue-boat", "rescue-drone"):
        telemetry = [
            (t, "telemetry", {"lat": lat, "lon": lon, "alt": alt, "mode": "GUIDED"})
            for t, (lat, lon, alt) in RESCUE[name]
        ]
        rows = sorted(telemetry + others[name], key=lambda row: row[0])
        outcome = record_batch_store(
            vehicle_id=vehicles[name].pk,
            message=Record(
                id=f"record:{session.pk}:1",
                session_id=str(session.pk),
                first=1,
                samples=[
                    Sample(seq=n, t=RESCUE_T0 + t, kind=kind, data=data)
                    for n, (t, kind, data) in enumerate(rows, start=1)
                ],
            ),
        )
        assert outcome.ok, outcome
    session_end(session=session, reason="the person was brought ashore", by_user=True)
    return session


def _at(name: str, t: float) -> list[float]:
    """Where :data:`RESCUE` has vehicle ``name`` at ``t`` s: its last position then."""
    lat, lon, _ = [p for s, p in RESCUE[name] if s <= t][-1]
    return [lat, lon]


@needs_chromium
async def test_the_replay_of_a_two_vehicle_rescue_shows_each_vehicle_on_its_own_track():
    """A search drone and a rescue boat, replayed: a track and a named marker each, in
    its own colour; at the slider's instant each vehicle is at its last position then
    (the boat not yet shown before it set out), with its own gauges; the timeline names
    the vehicle of each entry, in time order."""
    session = await db(_rescue_recorded)
    steps = sorted(t for track in RESCUE.values() for t, _ in track)
    with platform_server() as platform:
        async with chromium_browser() as browser:
            page = await browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            await sign_in(page, platform.base, "rita", password="pw-for-tests")
            await page.goto(f"{platform.base}/sessions/{session.pk}/replay/")
            await expect(page.locator("#replay")).to_have_attribute("data-loaded", "true")
            await expect(page.locator("[data-replay-status]")).to_have_text(
                "16 positions of 2 vehicles, 3 commands and events"
            )
            assert await page.evaluate("() => window.IoUVReplay.times()") == [
                RESCUE_T0 + t for t in steps
            ]

            # Two tracks, in two colours, each with all of its vehicle's positions.
            tracks = page.locator("path.replay-track")
            await expect(tracks).to_have_count(2)
            colours = {await track.get_attribute("stroke") for track in await tracks.all()}
            assert len(colours) == 2, colours

            async def shows(at: float) -> None:
                """The slider on the step at ``at`` s: each vehicle that has set out by
                then is at its last position, its marker labelled with its name, and
                its gauges say its altitude."""
                await page.locator("[data-replay-slider]").fill(str(steps.index(at)))
                expected = {name: _at(name, at) for name in RESCUE if RESCUE[name][0][0] <= at}
                assert await page.evaluate("() => window.IoUVReplay.markers()") == expected
                await expect(page.locator("path.replay-marker")).to_have_count(len(expected))
                labels = page.locator(".map-label[data-replay-vehicle]")
                await expect(labels).to_have_count(len(expected))
                for name in expected:
                    await expect(labels.filter(has_text=name)).to_be_visible()
                for name, track in RESCUE.items():
                    column = await page.locator(
                        f'[data-replay-gauges] thead th:has-text("{name}")'
                    ).get_attribute("data-gauge-vehicle")
                    alt = page.locator(f'[data-gauge="alt"][data-gauge-vehicle="{column}"]')
                    if name in expected:
                        _, (_, _, metres) = [p for p in track if p[0] <= at][-1]
                        await expect(alt).to_have_text(f"{metres:.1f} m")
                    else:
                        await expect(alt).to_have_text("\N{EN DASH}")
                        position = page.locator(f'[data-gauge="at"][data-gauge-vehicle="{column}"]')
                        await expect(position).to_have_text("no position yet")

            await shows(0.0)  # only the drone has set out
            await shows(6.0)  # a drone step: the boat where it was half a second before
            await shows(8.5)  # a boat step: the drone where it was at 8 s

            # The timeline: in time order (the boat's record was stored first), each
            # entry naming its vehicle; a click moves the slider to that instant.
            items = page.locator("[data-replay-timeline] li")
            await expect(items).to_have_count(3)
            texts = [" ".join(t.split()) for t in await items.all_text_contents()]
            assert "rescue-drone · user · take_off · ok" in texts[0], texts
            assert "rescue-drone · event · person_found" in texts[1], texts
            assert "rescue-boat · user · go_to · ok" in texts[2], texts
            await items.nth(2).get_by_role("button").click()
            assert await page.evaluate("() => window.IoUVReplay.markers()") == {
                "rescue-drone": _at("rescue-drone", 6.2),
                "rescue-boat": _at("rescue-boat", 6.2),
            }
            assert await page.locator("[data-replay-slider]").input_value() == str(steps.index(6.0))
            assert not errors, errors


@pytest.mark.realtime
async def test_an_uplink_cut_of_30_s_mid_flight_loses_no_sample(flight):
    """The platform is away for 30 s (killed, then started again) while the drone flies:
    the vehicle keeps the record meanwhile and the platform gets all of it."""
    platform, agent, quad, service = flight
    await agent_registered(quad, within=20, positioned=True)
    session, user_task = await session_deployed(agent, service)
    await _fly_through_an_outage(
        platform, agent, user_task.control_url, user_task.grant, outage_s=30
    )
    samples = await _all_uploaded(agent, session, ended=True)
    assert [s.seq for s in samples] == list(range(1, len(samples) + 1))
    assert not [s for s in samples if s.kind == "dropped"]
    # The cut is in the record: telemetry across it, with no hole (five a second; a
    # saturated machine has stalled the agent's loop for 1.2 s, nothing like the cut).
    track = [s for s in samples if s.kind == "telemetry" and s.data["armed"]]
    gaps = [b.t - a.t for a, b in itertools.pairwise(track)]
    assert track[-1].t - track[0].t > 30 and max(gaps) < 3.0, max(gaps)
    check = await db(record_verify, session=session)
    assert check.ok, check.problems
