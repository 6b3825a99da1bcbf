"""A session's flight record in the formats pilots, tools and authorities read
(docs/records.md): GPX 1.1 and KML 2.2 tracks with altitude and time, CSV of the track,
the commands and the events, the MAVLink ``.tlog``, and one zip archive of everything
with the session's hash-chained log, its verification and the session's recorded video,
streamed as it is made.

Altitude is what the vehicle reports: metres above its home point (GPX ``ele``, KML
``relativeToGround``). Times are UTC, from the vehicle's clock.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import zipfile
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from typing import Any, Final
from xml.etree import ElementTree as ET

from django.core.serializers.json import DjangoJSONEncoder

from fleet.models import Vehicle
from services.models import Assignment, RecordBatch, RecordSample, Session
from services.records.keeping import record_samples, record_tlog, record_verify
from services.sessions.log import session_log
from services.sessions.video import RECORD_VIDEO
from services.sfu import Recording, sfu_recordings

GPX_NS = "http://www.topografix.com/GPX/1/1"
KML_NS = "http://www.opengis.net/kml/2.2"
GX_NS = "http://www.google.com/kml/ext/2.2"

TRACK_COLUMNS = (
    "vehicle", "seq", "time_utc", "lat", "lon", "alt", "heading", "speed", "battery",
    "mode", "armed", "roll", "pitch",
)  # fmt: skip
COMMAND_COLUMNS = (
    "vehicle", "seq", "time_utc", "source", "name", "args", "ok", "code", "error",
    "age_ms", "client_seq",
)  # fmt: skip
EVENT_COLUMNS = ("vehicle", "seq", "time_utc", "kind", "event", "data")


def _utc(t: float) -> str:
    """ISO 8601 UTC with milliseconds and a Z (what GPX and KML readers expect)."""
    return datetime.fromtimestamp(t, tz=UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def record_vehicles(session: Session) -> list[dict[str, str]]:
    """The vehicles of ``session``'s record, as the replay shows them and the exports
    name their tracks, each ``{"id", "name"}``: those
    given a role in it, in the order they were given one (released ones too: a
    session's assignments are kept), then any other that uploaded samples to it, by
    name. The order is the page's: the first vehicle keeps the one-vehicle page's
    colours."""
    named: dict[str, str] = {}
    assigned = (
        Assignment.objects.filter(session=session)
        .order_by("created_at", "pk")
        .values_list("vehicle_id", "vehicle__name")
    )
    # A record is only stored from a vehicle holding an assignment, but its samples
    # are what the page draws: a vehicle that recorded is named whatever became of it.
    recorded = (
        Vehicle.objects.filter(
            pk__in=RecordBatch.objects.filter(session=session).values("vehicle_id")
        )
        .order_by("name")
        .values_list("pk", "name")
    )
    for vehicle_id, name in [*assigned, *recorded]:
        named.setdefault(str(vehicle_id), name)
    return [{"id": vehicle_id, "name": name} for vehicle_id, name in named.items()]


def _track_names(session: Session) -> dict[str, str]:
    """Vehicle id -> a track's name: the vehicle's name as the replay shows it, and its
    id, which the CSV exports' ``vehicle`` column holds."""
    return {v["id"]: f"{v['name']} (vehicle {v['id']})" for v in record_vehicles(session)}


def track_points(session: Session) -> dict[str, list[RecordSample]]:
    """Each vehicle's telemetry samples that have a position, in order."""
    tracks: dict[str, list[RecordSample]] = {}
    for sample in record_samples(session=session, kinds=["telemetry"]):
        if sample.data.get("lat") is not None and sample.data.get("lon") is not None:
            tracks.setdefault(str(sample.vehicle_id), []).append(sample)
    return tracks


def record_gpx(session: Session) -> bytes:
    """The track as GPX 1.1: one ``trk`` per vehicle, a ``trkpt`` per sample with
    ``ele`` (metres above home, when known) and ``time``."""
    ET.register_namespace("", GPX_NS)
    root = ET.Element(f"{{{GPX_NS}}}gpx", {"version": "1.1", "creator": "IoUV"})
    meta = ET.SubElement(root, f"{{{GPX_NS}}}metadata")
    ET.SubElement(meta, f"{{{GPX_NS}}}name").text = f"IoUV session {session.pk}"
    names = _track_names(session)
    for vehicle, points in track_points(session).items():
        trk = ET.SubElement(root, f"{{{GPX_NS}}}trk")
        ET.SubElement(trk, f"{{{GPX_NS}}}name").text = names.get(vehicle, f"vehicle {vehicle}")
        seg = ET.SubElement(trk, f"{{{GPX_NS}}}trkseg")
        for sample in points:
            d = sample.data
            pt = ET.SubElement(
                seg, f"{{{GPX_NS}}}trkpt", {"lat": repr(d["lat"]), "lon": repr(d["lon"])}
            )
            if d.get("alt") is not None:
                ET.SubElement(pt, f"{{{GPX_NS}}}ele").text = repr(float(d["alt"]))
            ET.SubElement(pt, f"{{{GPX_NS}}}time").text = _utc(sample.t)
    return bytes(ET.tostring(root, encoding="utf-8", xml_declaration=True))


def record_kml(session: Session) -> bytes:
    """The track as KML 2.2: a ``Placemark`` per vehicle holding a ``gx:Track`` (a
    ``when`` and a ``gx:coord`` "lon lat alt" per sample, altitude relative to the
    ground at home)."""
    ET.register_namespace("", KML_NS)
    ET.register_namespace("gx", GX_NS)
    root = ET.Element(f"{{{KML_NS}}}kml")
    doc = ET.SubElement(root, f"{{{KML_NS}}}Document")
    ET.SubElement(doc, f"{{{KML_NS}}}name").text = f"IoUV session {session.pk}"
    names = _track_names(session)
    for vehicle, points in track_points(session).items():
        placemark = ET.SubElement(doc, f"{{{KML_NS}}}Placemark")
        name = names.get(vehicle, f"vehicle {vehicle}")
        ET.SubElement(placemark, f"{{{KML_NS}}}name").text = name
        track = ET.SubElement(placemark, f"{{{GX_NS}}}Track")
        ET.SubElement(track, f"{{{KML_NS}}}altitudeMode").text = "relativeToGround"
        for sample in points:
            ET.SubElement(track, f"{{{KML_NS}}}when").text = _utc(sample.t)
        for sample in points:
            d = sample.data
            alt = float(d["alt"]) if d.get("alt") is not None else 0.0
            ET.SubElement(track, f"{{{GX_NS}}}coord").text = f"{d['lon']!r} {d['lat']!r} {alt!r}"
    return bytes(ET.tostring(root, encoding="utf-8", xml_declaration=True))


def _csv(columns: tuple[str, ...], rows: Iterator[dict[str, Any]]) -> bytes:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return out.getvalue().encode()


def _sample_rows(
    session: Session, kind: list[str], fields: Callable[[RecordSample], dict[str, Any]]
) -> Iterator[dict[str, Any]]:
    """One CSV row per sample of the given kinds, in order: the columns every CSV
    shares (``vehicle``, ``seq``, ``time_utc``) and then what ``fields`` reads from
    the sample."""
    for s in record_samples(session=session, kinds=kind):
        yield {"vehicle": s.vehicle_id, "seq": s.seq, "time_utc": _utc(s.t), **fields(s)}


def _track_fields(s: RecordSample) -> dict[str, Any]:
    return {c: s.data.get(c) for c in TRACK_COLUMNS[3:]}


def _command_fields(s: RecordSample) -> dict[str, Any]:
    d = s.data
    return {
        "source": d.get("source"),
        "name": d.get("name"),
        "args": json.dumps(d.get("args", {}), sort_keys=True),
        "ok": d.get("ok"),
        "code": d.get("code"),
        "error": d.get("error"),
        "age_ms": d.get("age_ms"),
        "client_seq": d.get("seq"),
    }


def _event_fields(s: RecordSample) -> dict[str, Any]:
    data = dict(s.data)
    return {
        "kind": s.kind,
        "event": data.pop("event", ""),
        "data": json.dumps(data, sort_keys=True),
    }


def record_track_csv(session: Session) -> bytes:
    """Every telemetry sample, one row each (positions missing left empty)."""
    return _csv(TRACK_COLUMNS, _sample_rows(session, ["telemetry"], _track_fields))


def record_commands_csv(session: Session) -> bytes:
    """Every command: who sent it (``source``), its acknowledgement, its age."""
    return _csv(COMMAND_COLUMNS, _sample_rows(session, ["command"], _command_fields))


def record_events_csv(session: Session) -> bytes:
    """The vehicle's events (refusals, envelope interventions, fail-safes) and what
    the record says it dropped."""
    return _csv(EVENT_COLUMNS, _sample_rows(session, ["event", "dropped"], _event_fields))


#: What the archive says when the session has no converted video.
NO_VIDEO: Final = (
    "No video was recorded for this session (the platform runs no SFU, the vehicle "
    "published no camera, or the recording is not converted yet)."
)
#: Bytes read from a video file at a time: what the archive holds in memory of it.
VIDEO_CHUNK: Final = 1 << 20


class _Spool:
    """Where the streamed zip is written: an unseekable sink (so :mod:`zipfile` writes
    each entry's sizes and CRC after its data) whose bytes are taken out as they come."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []

    def write(self, data: bytes, /) -> int:
        self._parts.append(bytes(data))
        return len(data)

    def flush(self) -> None:
        return None

    def close(self) -> None:
        return None

    def take(self) -> bytes:
        data, self._parts = b"".join(self._parts), []
        return data


def _listed(name: str, body: bytes) -> dict[str, Any]:
    return {"name": name, "size": len(body), "sha256": hashlib.sha256(body).hexdigest()}


def record_archive(session: Session) -> Iterator[bytes]:
    """One zip, in pieces as it is made: every export above, the samples as uploaded
    (``samples.jsonl``), the session's log with its hash chain (``log.json``), the
    check of the record against it (``verification.json``), the session's recorded
    video (``video/<n>.webm``, or ``.mp4`` for H.264: the stretches the replay plays,
    oldest first, stored as they are) and ``manifest.json``: every other file's name,
    size and SHA-256, and whether there is video (``video.recorded``; its stretches'
    start times and the ``log_seq`` of the log's event that chains each, or why there
    is none). A video is read a megabyte at a time, so a long one never sits in memory
    whole."""
    events = session_log(session=session)
    log = [
        {
            "seq": e.seq,
            "kind": e.kind,
            "data": e.data,
            "created_at": e.created_at,
            "occurred_at": e.occurred_at,
            "prev_hash": e.prev_hash,
            "hash": e.hash,
        }
        for e in events
    ]
    chained = {str(e.data.get("name")): e.seq for e in events if e.kind == RECORD_VIDEO}
    samples = "".join(
        json.dumps(
            {"vehicle": str(s.vehicle_id), "seq": s.seq, "t": s.t, "kind": s.kind, "data": s.data},
            sort_keys=True,
        )
        + "\n"
        for s in record_samples(session=session)
    )
    files: list[tuple[str, bytes]] = [
        ("track.gpx", record_gpx(session)),
        ("track.kml", record_kml(session)),
        ("track.csv", record_track_csv(session)),
        ("commands.csv", record_commands_csv(session)),
        ("events.csv", record_events_csv(session)),
    ]
    tlog = record_tlog(session=session)
    if tlog:
        files.append(("flight.tlog", tlog))
    files += [
        ("samples.jsonl", samples.encode()),
        ("log.json", json.dumps(log, cls=DjangoJSONEncoder, indent=1).encode()),
        # Every byte of the video hashed against the chain (the record's page checks
        # sizes only): the archive is what goes to an investigator, and it reads every
        # byte of the video anyway to send it.
        (
            "verification.json",
            json.dumps(record_verify(session=session, video="sha256").as_dict(), indent=1).encode(),
        ),
    ]
    # Everything that reads the database is done here, in the request; what the
    # iterator does as the answer goes out is reading the video files and zipping.
    recordings = sfu_recordings(session_id=session.pk)
    return _archive_stream(str(session.pk), files, recordings, chained)


def _archive_stream(
    session_id: str,
    files: list[tuple[str, bytes]],
    recordings: list[Recording],
    chained: dict[str, int],
) -> Iterator[bytes]:
    """The zip of ``files`` and the video ``recordings`` and the manifest (see
    :func:`record_archive`), a piece at a time. ``chained``: the file name of each
    stretch the session's log chains -> that event's ``seq``."""
    listed = [_listed(name, body) for name, body in files]
    stretches: list[dict[str, Any]] = []
    spool = _Spool()
    with zipfile.ZipFile(spool, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, body in files:
            archive.writestr(name, body)
            yield spool.take()
        for index, recording in enumerate(recordings):
            name = f"video/{index}{recording.path.suffix}"
            info = zipfile.ZipInfo.from_file(recording.path, name)
            info.compress_type = zipfile.ZIP_STORED  # WebM is compressed already
            digest, size = hashlib.sha256(), 0
            with recording.path.open("rb") as source, archive.open(info, "w") as entry:
                while chunk := source.read(VIDEO_CHUNK):
                    entry.write(chunk)
                    digest.update(chunk)
                    size += len(chunk)
                    yield spool.take()
            listed.append({"name": name, "size": size, "sha256": digest.hexdigest()})
            stretches.append(
                {
                    "name": name,
                    "started_at": recording.started_at,
                    "started_utc": _utc(recording.started_at),
                    # Where log.json holds its size and SHA-256 (null: not chained,
                    # which verification.json reports).
                    "log_seq": chained.get(recording.path.name),
                }
            )
        video: dict[str, Any] = {"recorded": bool(stretches), "stretches": stretches}
        if not stretches:
            video["detail"] = NO_VIDEO
        manifest = {"session": session_id, "files": listed, "video": video}
        archive.writestr("manifest.json", json.dumps(manifest, indent=1))
    yield spool.take()
