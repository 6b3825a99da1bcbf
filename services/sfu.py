"""The platform's SFU (Janus's VideoRoom plugin): a room per session, who may publish
and subscribe in it, and its recording (docs/video.md, "The SFU").

The pilot's picture comes straight from the vehicle; everyone else watches the one copy
the vehicle publishes to Janus. The platform is the only one that can make rooms (the
plugin's ``admin_key``); Janus checks, by itself, every request of a vehicle or a
spectator:

* **core token** (``token_auth`` with ``token_auth_secret``): every request must carry a
  token ``<expiry>,janus,janus.plugin.videoroom:<base64 HMAC-SHA1>`` that only the
  platform can sign. Minted for a vehicle with its task, and for a user with a viewer
  grant; it expires by itself, nothing is stored on either side (as TURN credentials,
  services.ice). A forged or missing one is refused before any room is reached.
* **room pin**: each session's room has its own pin, so a token holder of one session
  cannot watch another.
* **publish token** (the room's ``allowed`` list): only the vehicle publishes.

Room id, pin, room secret and publish token are derived from the session id with the
admin key (HMAC), so nothing is stored and a room lost with a Janus restart is made again
the same (:func:`sfu_room_open` is idempotent). Each room records what the vehicle
publishes into ``IOUV_JANUS_REC_DIR/<session hex>/`` (Janus's ``.mjr`` files);
:func:`sfu_recording_convert` turns them into WebM with ``janus-pp-rec`` once the
session has ended (services.sessions.video, which also chains each converted stretch
into the session's log).
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import hmac
import json
import logging
import re
import secrets
import shutil
import subprocess
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any, Final

from celery import shared_task
from django.conf import settings
from django.db import transaction

from agents.protocol import SfuPublish

log = logging.getLogger(__name__)

PLUGIN: Final = "janus.plugin.videoroom"
#: The vehicle's publisher id in its session's room (one publisher per room).
FEED: Final = 1
#: How long the platform waits for Janus's HTTP API.
TIMEOUT_S: Final = 5.0
#: VideoRoom's codes: the room exists already; there is no such room.
ROOM_EXISTS: Final = 427
NO_SUCH_ROOM: Final = 426
#: Janus names a publisher's recording ``videoroom-<room>-user-<id>-<start µs>-video-<n>.mjr``.
_RECORDING = re.compile(r"-user-\d+-(?P<start_us>\d+)-video-\d+\.mjr$")


class SfuError(Exception):
    """Janus could not be reached, or refused what the platform asked."""


def sfu_configured() -> bool:
    """Whether spectators watch through an SFU (its URLs and both secrets are set)."""
    return bool(
        settings.IOUV_JANUS_URL
        and settings.IOUV_JANUS_PUBLIC_URL
        and settings.IOUV_JANUS_TOKEN_SECRET
        and settings.IOUV_JANUS_ADMIN_KEY
    )


def janus_token(*, expires_at: float) -> str:
    """A Janus core token for the VideoRoom plugin, valid until ``expires_at`` (Unix
    seconds), signed with ``IOUV_JANUS_TOKEN_SECRET`` as Janus's signed-token mode
    checks it."""
    data = f"{int(expires_at)},janus,{PLUGIN}"
    key = settings.IOUV_JANUS_TOKEN_SECRET.encode()
    signature = hmac.new(key, data.encode(), hashlib.sha1).digest()
    return f"{data}:{base64.b64encode(signature).decode()}"


def _derived(purpose: str, session_id: Any) -> str:
    key = settings.IOUV_JANUS_ADMIN_KEY.encode()
    text = f"iouv-sfu:{purpose}:{uuid.UUID(str(session_id)).hex}"
    return hmac.new(key, text.encode(), hashlib.sha256).hexdigest()[:32]


def sfu_room(session_id: Any) -> int:
    """The session's room id: 52 bits of its UUID (a browser reads it exactly)."""
    return int(uuid.UUID(str(session_id)).hex[:13], 16) or 1


def sfu_recording_dir(session_id: Any) -> Path | None:
    """Where Janus records the session's room; None when nothing is recorded."""
    if not settings.IOUV_JANUS_REC_DIR:
        return None
    return Path(settings.IOUV_JANUS_REC_DIR) / uuid.UUID(str(session_id)).hex


def sfu_publish_for(*, session_id: Any) -> SfuPublish | None:
    """What the vehicle's task says about publishing (None without an SFU)."""
    if not sfu_configured():
        return None
    return SfuPublish(
        url=settings.IOUV_JANUS_PUBLIC_URL,
        token=janus_token(expires_at=time.time() + settings.IOUV_JANUS_TOKEN_TTL_S),
        room=sfu_room(session_id),
        feed=FEED,
        publish_token=_derived("publish", session_id),
        pin=_derived("pin", session_id),
    )


def sfu_viewer_for(*, session_id: Any) -> dict[str, Any] | None:
    """What a spectator's page needs to subscribe (None without an SFU): call it only
    for a user who was just given a viewer grant on the session."""
    if not sfu_configured():
        return None
    return {
        "url": settings.IOUV_JANUS_PUBLIC_URL,
        "token": janus_token(expires_at=time.time() + settings.IOUV_JANUS_TOKEN_TTL_S),
        "room": sfu_room(session_id),
        "feed": FEED,
        "pin": _derived("pin", session_id),
    }


def _post(url: str, body: dict[str, Any]) -> dict[str, Any]:
    request = urllib.request.Request(
        url,
        data=json.dumps({**body, "transaction": secrets.token_hex(6)}).encode(),
        headers={"Content-Type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=TIMEOUT_S) as response:
            answer: dict[str, Any] = json.loads(response.read())
    except (OSError, ValueError) as exc:
        raise SfuError(f"the SFU at {url} did not answer: {exc}") from exc
    if answer.get("janus") == "error":
        error = answer.get("error", {})
        raise SfuError(f"the SFU refused: {error.get('code')} {error.get('reason')}")
    return answer


def _videoroom(body: dict[str, Any]) -> dict[str, Any]:
    """One synchronous VideoRoom request over Janus's HTTP API, in a session of its
    own (create, attach, message, destroy). Returns the plugin's data, errors included."""
    base = settings.IOUV_JANUS_URL.rstrip("/")
    token = janus_token(expires_at=time.time() + 60)
    session = _post(base, {"janus": "create", "token": token})["data"]["id"]
    try:
        handle = _post(f"{base}/{session}", {"janus": "attach", "plugin": PLUGIN, "token": token})
        answer = _post(
            f"{base}/{session}/{handle['data']['id']}",
            {"janus": "message", "body": body, "token": token},
        )
        data: dict[str, Any] = answer.get("plugindata", {}).get("data", {})
        return data
    finally:
        try:
            _post(f"{base}/{session}", {"janus": "destroy", "token": token})
        except SfuError:
            log.info("could not destroy a Janus session of the platform's", exc_info=True)


def sfu_room_open(*, session_id: Any) -> bool:
    """Make the session's room (idempotent): one publisher (the vehicle, by its publish
    token), the session's pin, VP8, recording into :func:`sfu_recording_dir`. Returns
    True when it was made now, False when it was there already. Raises SfuError when
    Janus is away or refuses."""
    if not sfu_configured():
        raise SfuError("no SFU is configured")
    body: dict[str, Any] = {
        "request": "create",
        "room": sfu_room(session_id),
        "admin_key": settings.IOUV_JANUS_ADMIN_KEY,
        "description": f"session {uuid.UUID(str(session_id)).hex[:8]}",
        "secret": _derived("secret", session_id),
        "pin": _derived("pin", session_id),
        "allowed": [_derived("publish", session_id)],
        "publishers": 1,
        # The vehicle sends one of them (its video.codec); spectators get that one.
        "videocodec": "vp8,h264",
        "audiocodec": "opus",
        "bitrate": 0,
        "notify_joining": False,
        # Only the platform (the room's secret) may turn recording on or off.
        "lock_record": True,
    }
    directory = sfu_recording_dir(session_id)
    if directory is not None:
        body |= {"record": True, "rec_dir": str(directory)}
    data = _videoroom(body)
    if data.get("error_code") == ROOM_EXISTS:
        return False
    if "error_code" in data:
        raise SfuError(f"the SFU refused the room: {data.get('error')}")
    return True


def sfu_room_close(*, session_id: Any) -> bool:
    """Destroy the session's room: its spectators and publisher are dropped and its
    recording is closed. Returns False when there was no such room. Raises SfuError."""
    data = _videoroom(
        {
            "request": "destroy",
            "room": sfu_room(session_id),
            "secret": _derived("secret", session_id),
        }
    )
    if data.get("error_code") == NO_SUCH_ROOM:
        return False
    if "error_code" in data:
        raise SfuError(f"the SFU refused to close the room: {data.get('error')}")
    return True


def sfu_room_schedule(*, session_id: Any) -> None:
    """Make the session's room from a Celery task once the current transaction commits
    (retried while Janus is away)."""
    transaction.on_commit(lambda: services_sfu_room_open.delay(str(session_id)), robust=True)


def sfu_rooms_ensure() -> int:
    """Make the room of every live session whose vehicle publishes, where Janus lost it
    (a restart): the vehicle, which keeps trying, then publishes and is recorded again
    even if no spectator comes to make the room. Returns how many rooms were made.
    Raises SfuError when Janus is away (the next run tries again)."""
    from services.models import Session  # models import nothing of this module's users

    if not sfu_configured():
        return 0
    sessions = (
        Session.objects.filter(
            state__in=[Session.State.ASSIGNED, Session.State.ACTIVE],
            assignments__active=True,
            assignments__vehicle__profile__video=True,
            assignments__vehicle__profile__sfu=True,
        )
        .values_list("pk", flat=True)
        .distinct()
    )
    return sum(sfu_room_open(session_id=pk) for pk in sessions)


def sfu_recording_delete(*, session_id: Any) -> bool:
    """Delete the session's recorded video (its folder); False when there was none."""
    directory = sfu_recording_dir(session_id)
    if directory is None or not directory.is_dir():
        return False
    shutil.rmtree(directory)
    return True


def sfu_recorded_sessions() -> list[uuid.UUID]:
    """The sessions that have a recording folder (for the record's retention)."""
    if not settings.IOUV_JANUS_REC_DIR or not Path(settings.IOUV_JANUS_REC_DIR).is_dir():
        return []
    found = []
    for entry in Path(settings.IOUV_JANUS_REC_DIR).iterdir():
        try:
            found.append(uuid.UUID(hex=entry.name))
        except ValueError:
            continue  # not a session's folder
    return found


#: The container a recording is converted to, by the codec the vehicle sent, and the
#: MIME type a browser plays it as.
CONTAINERS: dict[str, tuple[str, str]] = {
    "vp8": (".webm", "video/webm"),
    "h264": (".mp4", "video/mp4"),
}


@dataclasses.dataclass(frozen=True)
class Recording:
    """One stretch of a session's video (a new one each time the vehicle published
    again): the playable file (WebM for VP8, MP4 for H.264), and when its first frame
    was received (Unix seconds)."""

    path: Path
    started_at: float

    @property
    def content_type(self) -> str:
        """The file's MIME type, as a browser plays it."""
        for suffix, content_type in CONTAINERS.values():
            if self.path.suffix == suffix:
                return content_type
        return "application/octet-stream"


def sfu_recordings(*, session_id: Any) -> list[Recording]:
    """The session's converted recordings, oldest first."""
    directory = sfu_recording_dir(session_id)
    if directory is None or not directory.is_dir():
        return []
    found = []
    for suffix, _ in CONTAINERS.values():
        for converted in directory.glob(f"*{suffix}"):
            if converted.name.endswith(f".part{suffix}"):
                continue
            mjr = converted.with_suffix(".mjr")
            match = _RECORDING.search(mjr.name)
            if match:
                started = _first_packet_at(mjr) or int(match["start_us"]) / 1e6
                found.append(Recording(converted, started))
    return sorted(found, key=lambda r: r.started_at)


def _mjr_header(mjr: Path) -> dict[str, Any] | None:
    """The ``.mjr`` file's header (``MJR00002``, a 2-byte length, then JSON: ``c`` the
    codec, ``u`` when the first packet was written, µs), or None when unreadable."""
    try:
        with mjr.open("rb") as f:
            head = f.read(8 + 2)
            if len(head) < 10 or not head.startswith(b"MJR00002"):
                return None
            info = json.loads(f.read(int.from_bytes(head[8:10], "big")))
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) else None


def _first_packet_at(mjr: Path) -> float | None:
    """When Janus wrote the recording's first packet (Unix seconds): the converted
    file's time 0."""
    first = (_mjr_header(mjr) or {}).get("u")
    return first / 1e6 if isinstance(first, int) and first > 0 else None


def sfu_recording_convert(*, session_id: Any) -> list[Recording]:
    """Convert the session's ``.mjr`` recordings not yet converted (``janus-pp-rec``,
    package janus-tools, to WebM or MP4 by the codec: :data:`CONTAINERS`); idempotent.
    Returns all its recordings. Raises SfuError when janus-pp-rec is missing or fails on
    a file."""
    directory = sfu_recording_dir(session_id)
    if directory is None or not directory.is_dir():
        return []
    tool = shutil.which("janus-pp-rec")
    if tool is None:
        raise SfuError("janus-pp-rec is not installed (Debian package janus-tools)")
    for mjr in sorted(directory.glob("*-video-*.mjr")):
        if any(mjr.with_suffix(suffix).exists() for suffix, _ in CONTAINERS.values()):
            continue  # converted already: its header need not be read again
        codec = (_mjr_header(mjr) or {}).get("c", "vp8")
        suffix = CONTAINERS.get(codec, CONTAINERS["vp8"])[0]
        converted = mjr.with_suffix(suffix)
        partial = mjr.with_suffix(f".part{suffix}")
        done = subprocess.run(
            [tool, str(mjr), str(partial)], capture_output=True, text=True, timeout=600
        )
        if done.returncode != 0 or not partial.exists():
            partial.unlink(missing_ok=True)
            if mjr.stat().st_size <= 8:  # a header only: the publisher never sent a frame
                continue
            raise SfuError(f"janus-pp-rec failed on {mjr.name}: {done.stderr[-300:]}")
        partial.rename(converted)  # whole or not at all, for a reader of the folder
    return sfu_recordings(session_id=session_id)


# --- Celery tasks (services.tasks lists and schedules them) ---------------------------
# Here, not in services.tasks: the sessions deploying a task schedule them, and
# services.tasks imports the sessions' code, so importing it from here would close a
# cycle. The task that closes an ended session's room and converts its recording is
# services.sessions.video's: it also chains the video into the session's log.


@shared_task(
    name="services.sfu_room_open",
    acks_late=True,
    autoretry_for=(SfuError,),
    max_retries=10,
    retry_backoff=2,
    retry_backoff_max=60,
    retry_jitter=True,
)
def services_sfu_room_open(session_id: str) -> bool:
    """Make a live session's SFU room (idempotent); retried while Janus is away.
    Nothing for a session that has ended meanwhile (its end time is set)."""
    from services.models import Session  # models import nothing of this module's users

    if not Session.objects.filter(pk=session_id, ended_at__isnull=True).exists():
        return False
    return sfu_room_open(session_id=session_id)


@shared_task(name="services.sfu_rooms_ensure")
def services_sfu_rooms_ensure() -> int:
    """Make again the SFU rooms a restarted Janus lost (nothing without an SFU)."""
    try:
        return sfu_rooms_ensure()
    except SfuError as exc:  # Janus away: the next run tries again
        log.info("SFU rooms not checked: %s", exc)
        return 0
