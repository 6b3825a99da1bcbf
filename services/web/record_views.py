"""The portal's flight-record answers: a session's record summarised with its check,
and its exports (services.records.exports). Who may open them: the session's user,
monitors, admins (services.records.keeping.record_visible); anyone else is told there is no
such session (404)."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Final

from asgiref.sync import sync_to_async
from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.core.handlers.asgi import ASGIRequest
from django.http import (
    Http404,
    HttpRequest,
    HttpResponse,
    JsonResponse,
    StreamingHttpResponse,
)
from django.http.response import HttpResponseBase
from django.shortcuts import get_object_or_404, render
from django.urls import reverse
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET

from accounts.users import AuthenticatedHttpRequest
from fleet.models import Vehicle
from services.models import RecordSample, Session
from services.records import exports
from services.records.keeping import record_tlog, record_verify, record_visible
from services.sfu import sfu_recordings

#: Export name -> (builder, content type, file name suffix). A builder returns the
#: whole file, or (the zip, which holds the session's video) an iterator of its pieces.
EXPORTS: Final[dict[str, tuple[Callable[[Session], bytes | Iterator[bytes]], str, str]]] = {
    "gpx": (exports.record_gpx, "application/gpx+xml", "track.gpx"),
    "kml": (exports.record_kml, "application/vnd.google-earth.kml+xml", "track.kml"),
    "track.csv": (exports.record_track_csv, "text/csv; charset=utf-8", "track.csv"),
    "commands.csv": (exports.record_commands_csv, "text/csv; charset=utf-8", "commands.csv"),
    "events.csv": (exports.record_events_csv, "text/csv; charset=utf-8", "events.csv"),
    "tlog": (lambda s: record_tlog(session=s), "application/octet-stream", "flight.tlog"),
    "zip": (exports.record_archive, "application/zip", "record.zip"),
}


def record_session(*, user: object, session_id: object) -> Session:
    """The session whose record ``user`` may open; Http404 otherwise (other users'
    sessions are not even confirmed to exist)."""
    session = get_object_or_404(Session.objects.select_related("service"), pk=session_id)
    if not record_visible(session=session, user=user):
        raise Http404("no such session")
    return session


def record_file(request: HttpRequest, session: Session, name: str) -> HttpResponseBase:
    """The export ``name`` of ``session``'s record as a download; Http404 for an
    unknown name, or a ``.tlog`` the record does not have. The zip is streamed as it is
    made (:func:`streamed`)."""
    if name not in EXPORTS:
        raise Http404("no such export")
    build, content_type, suffix = EXPORTS[name]
    body = build(session)
    if name == "tlog" and not body:
        raise Http404("this record has no MAVLink log")
    response: HttpResponseBase
    if isinstance(body, bytes):
        response = HttpResponse(body, content_type=content_type)
    else:
        response = StreamingHttpResponse(streamed(request, body), content_type=content_type)
    response["Content-Disposition"] = f'attachment; filename="session-{session.pk}-{suffix}"'
    return response


def streamed(
    request: HttpRequest, pieces: Iterator[bytes]
) -> Iterator[bytes] | AsyncIterator[bytes]:
    """``pieces`` as a streaming answer's content. Under WSGI (production's gunicorn)
    as they are. Under ASGI (``iouv.serve``) an asynchronous iterator that takes them
    one at a time in a worker thread: Django reads a synchronous iterator whole before
    sending any of it there, which for a zip holding hours of video means all of it in
    memory. ``pieces`` must not touch the database (the thread is any)."""
    if isinstance(request, ASGIRequest):
        return _pulled(pieces)
    return pieces


def _next(pieces: Iterator[bytes]) -> bytes | None:
    return next(pieces, None)


async def _pulled(pieces: Iterator[bytes]) -> AsyncIterator[bytes]:
    take = sync_to_async(_next, thread_sensitive=False)
    try:
        while (piece := await take(pieces)) is not None:
            yield piece
    finally:
        close = getattr(pieces, "close", None)
        if close is not None:  # a generator: its files are closed (a client gone)
            await sync_to_async(close, thread_sensitive=False)()


def record_summary(session: Session, *, url_for: Callable[[str], str]) -> dict[str, object]:
    """How much the record holds (samples by kind), its check, and where its exports
    are (``url_for(export name)``; no ``tlog`` without a MAVLink log)."""
    counts: dict[str, int] = {}
    for kind in RecordSample.objects.filter(session=session).values_list("kind", flat=True):
        counts[kind] = counts.get(kind, 0) + 1
    exports_urls = {name: url_for(name) for name in EXPORTS if name != "tlog" or counts.get("tlog")}
    return {
        "session": str(session.pk),
        "samples": counts,
        # The video checked by size only: this answers every view of the record (portal
        # and API), and hashing reads every byte of every stretch (an hour of video is
        # hundreds of megabytes: seconds of disk and CPU a view). A stat still catches a
        # video gone, cut short or replaced by one of another size; the zip's
        # verification.json (exports.record_archive) checks every byte.
        "verification": record_verify(session=session, video="size").as_dict(),
        "exports": exports_urls,
    }


@never_cache
@login_required
@require_GET
def session_record(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The record's summary (JSON)."""
    session = record_session(user=request.user, session_id=session_id)
    summary = record_summary(
        session, url_for=lambda name: reverse("session_record_export", args=[session.pk, name])
    )
    summary["replay"] = reverse("session_replay", args=[session.pk])
    return JsonResponse(summary)


@never_cache
@login_required
@require_GET
def session_record_export(
    request: AuthenticatedHttpRequest, session_id: str, name: str
) -> HttpResponseBase:
    """One export of the record (GPX, KML, CSV, tlog, zip)."""
    return record_file(request, record_session(user=request.user, session_id=session_id), name)


#: Samples one replay answer holds at most; the page asks again from the last one.
REPLAY_PAGE: Final = 2000
#: What the replay page shows of each kind (tlog pieces are for tools, not the page).
REPLAY_KINDS: Final = ("telemetry", "command", "event", "dropped")


def replay_samples(session: Session, *, after: int) -> dict[str, object]:
    """The record's samples the replay page shows that were stored after the sample
    whose ``id`` is ``after`` (0: from the start), at most :data:`REPLAY_PAGE`, in the
    order they were stored; ``more`` says whether the page should ask again at once,
    ``vehicles`` names the vehicles of these samples (id -> name: one may have been
    given a role after the page was opened).
    The cursor is the stored row's id rather than the vehicle's sequence number, so a
    session with several vehicles (each numbering its own) still has one cursor."""
    rows = list(
        RecordSample.objects.filter(session=session, kind__in=REPLAY_KINDS, pk__gt=after)
        .order_by("pk")
        .values("pk", "vehicle_id", "seq", "t", "kind", "data")[: REPLAY_PAGE + 1]
    )
    more = len(rows) > REPLAY_PAGE
    rows = rows[:REPLAY_PAGE]
    names = Vehicle.objects.filter(pk__in={r["vehicle_id"] for r in rows}).values_list("pk", "name")
    return {
        "samples": [
            {
                "id": r["pk"],
                "vehicle": str(r["vehicle_id"]),
                "seq": r["seq"],
                "t": r["t"],
                "kind": r["kind"],
                "data": r["data"],
            }
            for r in rows
        ],
        "vehicles": {str(pk): name for pk, name in names},
        "next": rows[-1]["pk"] if rows else after,
        "more": more,
        # Still recording: the page keeps asking for what comes next.
        "live": session.state
        in (Session.State.REQUESTED, Session.State.ASSIGNED, Session.State.ACTIVE),
    }


@never_cache
@login_required
@require_GET
def session_replay(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """The replay page: each vehicle's track on the map, a time slider, the gauges of
    each vehicle at that instant, the commands and events on a timeline
    (static/js/replay.js draws it from :func:`session_replay_samples`; the vehicles it
    names are :func:`replay_vehicles`)."""
    session = record_session(user=request.user, session_id=session_id)
    return render(
        request,
        "services/replay.html",
        {
            "session": session,
            "replay": {
                "samples_url": reverse("session_replay_samples", args=[session.pk]),
                "vehicles": exports.record_vehicles(session),
                "tiles": settings.IOUV_MAP_TILES_URL,
                "poll_ms": 2000,
                # What the SFU recorded, converted once the session ended: each stretch
                # (a new one after the vehicle published again) with when it started,
                # so the page plays it in step with the track.
                "videos": [
                    {
                        "url": reverse("session_replay_video", args=[session.pk, index]),
                        "started_at": recording.started_at,
                    }
                    for index, recording in enumerate(sfu_recordings(session_id=session.pk))
                ],
            },
        },
    )


@never_cache
@login_required
@require_GET
def session_replay_samples(request: AuthenticatedHttpRequest, session_id: str) -> HttpResponse:
    """JSON: :func:`replay_samples` after ``?after=<id>`` (a whole number; 400 if not)."""
    session = record_session(user=request.user, session_id=session_id)
    raw = request.GET.get("after", "0")
    if not raw.isdigit():
        return JsonResponse({"error": "after must be a whole number (a sample id)"}, status=400)
    return JsonResponse(replay_samples(session, after=int(raw)))


@never_cache
@login_required
@require_GET
def session_replay_video(
    request: AuthenticatedHttpRequest, session_id: str, index: int
) -> HttpResponseBase:
    """The ``index``-th stretch of the session's recorded video (WebM, or MP4 for H.264);
    404 when there is none (no SFU, nothing recorded, not converted yet)."""
    session = record_session(user=request.user, session_id=session_id)
    recordings = sfu_recordings(session_id=session.pk)
    if not 0 <= index < len(recordings):
        raise Http404("no such recording")
    recording = recordings[index]
    path = recording.path
    size = path.stat().st_size
    wanted = _byte_range(request.headers.get("Range", ""), size)
    start, end = wanted if wanted is not None else (0, size - 1)
    # Streamed as the zip is (:func:`streamed`), the whole file as a range: a
    # FileResponse, or any synchronous iterator, is read whole by Django under ASGI
    # before any of it is sent, which for an hour of video means all of it in memory.
    # (Under WSGI a whole file thus gives up the server's file wrapper, gunicorn's
    # sendfile, as a range always did: one code path and a bounded memory instead.)
    response = StreamingHttpResponse(
        streamed(request, _file_slice(path, start, end - start + 1)),
        status=200 if wanted is None else 206,
        content_type=recording.content_type,
    )
    if wanted is not None:
        # A player seeks by asking for bytes from where it wants to be: without ranges a
        # browser cannot seek at all (the replay's slider moves the video).
        response["Content-Range"] = f"bytes {start}-{end}/{size}"
    response["Content-Length"] = str(end - start + 1)
    response["Accept-Ranges"] = "bytes"
    return response


_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


def _byte_range(header: str, size: int) -> tuple[int, int] | None:
    """The one byte range ``header`` asks for, inclusive and within ``size``; None for
    no range, several, or one that makes no sense (the whole file is sent then)."""
    match = _RANGE.match(header.strip())
    if not match or size == 0 or not (match[1] or match[2]):
        return None
    if match[1]:
        start = int(match[1])
        end = min(int(match[2]), size - 1) if match[2] else size - 1
    else:  # the last N bytes
        start, end = max(0, size - int(match[2])), size - 1
    return (start, end) if start <= end < size else None


#: Bytes of a video sent at a time: what an answer holds of it in memory.
VIDEO_PIECE: Final = 1 << 16


def _file_slice(path: Path, start: int, length: int) -> Iterator[bytes]:
    """``length`` bytes of the file at ``path`` from ``start``, :data:`VIDEO_PIECE` at a
    time (fewer if the file is shorter). Opened when the first piece is asked for."""
    with path.open("rb") as f:
        f.seek(start)
        while length > 0:
            chunk = f.read(min(length, VIDEO_PIECE))
            if not chunk:
                return
            length -= len(chunk)
            yield chunk
