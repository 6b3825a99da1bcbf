"""Fixtures of the survey's tests: the seeded demo with quad-1 online, the drone played
by its reports and its photos (rendered by the simulated nadir camera where the plan
puts them) uploaded through the core's own keeper, as its agent would."""

from __future__ import annotations

import base64
import hashlib
import json
import math
from typing import Any

import pytest
from django.contrib.auth import get_user_model
from django.utils import timezone

from agents.geo import distance_m
from agents.missions.survey.runner import photo_name
from agents.missions.survey.spec import survey_photo_points
from agents.protocol import parse_message
from agents.protocol.messages import ARTIFACT_CHUNK_BYTES, Artifact
from agents.stills import NadirSimCamera, photo_jpeg
from fleet.models import Vehicle
from fleet.vehicle_events import vehicle_events
from kinds.survey.models import Survey
from kinds.survey.planning import plan_lines
from kinds.survey.workflow import survey_advance
from services.demo import demo_seed
from services.models import Assignment, Service, Session
from services.records.artifacts import artifact_chunk_store


def drones_online(*names: str) -> None:
    """The demo vehicles ``names`` online, idle at their station with a full battery."""
    for vehicle in Vehicle.objects.filter(name__in=names).select_related("station"):
        vehicle.status = Vehicle.Status.IDLE
        vehicle.last_seen = timezone.now()
        vehicle.lat, vehicle.lon, vehicle.alt = vehicle.station.lat, vehicle.station.lon, 0.0
        vehicle.battery = 99.0
        vehicle.save()


def heard_from(*vehicles: Vehicle) -> None:
    """``vehicles``' agents reported just now, as their heartbeats do all along (a
    vehicle not heard from for IOUV_OFFLINE_AFTER_S is not offered to a mission)."""
    Vehicle.objects.filter(pk__in=[v.pk for v in vehicles]).update(last_seen=timezone.now())


def spare_drone(name: str, *, like: str = "quad-1") -> Vehicle:
    """Another drone like ``like``, online at its station."""
    spare = Vehicle.objects.get(name=like)
    spare.pk, spare.name, spare.credential_hash = None, name, ""
    spare.save()
    drones_online(name)
    return spare


@pytest.fixture
def demo(client: Any) -> Service:
    """The seeded demo with quad-1 online, its client logged in; the survey service."""
    demo_seed(password="pw")
    drones_online("quad-1")
    client.force_login(get_user_model().objects.get(username="client"))
    return Service.objects.get(slug="aerial-survey")


def report(vehicle_id: Any, session: Session, event: str, **data: Any) -> None:
    """What the drone's agent says, through the uplink's handlers."""
    message = parse_message(
        json.dumps({"type": "event", "session_id": str(session.pk), "event": event, "data": data}),
        channel="uplink_to_platform",
    )
    vehicle_events().agent_message(vehicle_id=str(vehicle_id), message=message)


def surveyor(session: Session) -> Assignment:
    return Assignment.objects.select_related("vehicle").get(
        session=session, role="surveyor", active=True
    )


def upload(vehicle_id: Any, session: Session, name: str, jpeg: bytes, meta: dict[str, Any]) -> None:
    """A photo uploaded as the agent's ArtifactStore sends it, chunk by chunk."""
    count = -(-len(jpeg) // ARTIFACT_CHUNK_BYTES)
    for index in range(count):
        part = jpeg[index * ARTIFACT_CHUNK_BYTES : (index + 1) * ARTIFACT_CHUNK_BYTES]
        outcome = artifact_chunk_store(
            vehicle_id=vehicle_id,
            message=Artifact(
                id=f"artifact:{session.pk}:{name}:{index}",
                session_id=str(session.pk),
                name=name,
                media_type="image/jpeg",
                size=len(jpeg),
                sha256=hashlib.sha256(jpeg).hexdigest(),
                index=index,
                count=count,
                meta=meta,
                b64=base64.b64encode(part).decode(),
            ),
        )
        assert outcome.ok, outcome.detail


def fly(session: Session, photos: range | None = None, *, uploaded: bool = True) -> None:
    """The surveyor takes ``photos`` (default: from the next one to the last) where the
    plan puts them, facing along their line, with quad-1's camera (small pictures,
    the same optics), reports each and uploads it."""
    survey = Survey.objects.get(pk=session.pk)
    assignment = surveyor(session)
    plan = survey.plan
    assert plan is not None
    lines = plan_lines(plan)
    points = survey_photo_points(lines, plan["spacing_m"])
    camera = NadirSimCamera(hfov_deg=73.7, width=256, height=192, quality=85)
    for index in photos if photos is not None else range(survey.next_photo, len(points)):
        line, place = points[index]
        start, end = lines[line]
        north = (end[0] - start[0]) * 111_000
        east = (end[1] - start[1]) * 111_000 * math.cos(math.radians(start[0]))
        heading = math.degrees(math.atan2(east, north)) % 360 if distance_m(start, end) else 0.0
        pose = {"lat": place[0], "lon": place[1], "alt": plan["altitude_m"], "heading_deg": heading}
        meta = {
            "lat": place[0],
            "lon": place[1],
            "alt": plan["altitude_m"],
            "heading_deg": heading,
            "t": 1.8e9 + index,
            "width": 256,
            "height": 192,
            "hfov_deg": 73.7,
        }
        report(assignment.vehicle_id, session, "photo_taken", index=index, name=photo_name(index))
        if uploaded:
            jpeg = photo_jpeg(camera.render(pose), meta)
            upload(assignment.vehicle_id, session, photo_name(index), jpeg, meta)
        survey_advance(session.pk)
