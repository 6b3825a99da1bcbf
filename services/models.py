"""Service definitions and requirements, grants, sessions, assignments, session log."""

from __future__ import annotations

import uuid
from typing import Any

from django.conf import settings
from django.contrib.auth.models import Group
from django.core.exceptions import ValidationError
from django.core.validators import MaxValueValidator, MinValueValidator
from django.db import models
from django.db.models import Q

from fleet.attributes import (
    ATTRIBUTES,
    CAMERAS,
    ENVIRONMENTS,
    FEATURES,
    ChoiceListValidator,
    NumberAttribute,
)
from fleet.models import Vehicle, VehicleType
from services.kinds import UnknownKind, kind_named, kinds


def _kind_installed(value: str) -> None:
    try:
        kind_named(value)
    except UnknownKind:
        known = ", ".join(k.name for k in kinds()) or "none"
        raise ValidationError(
            f"no service kind {value!r} is installed (installed: {known})"
        ) from None


class Service(models.Model):
    """Something a user can ask the fleet to do, and the rules it runs under."""

    class Failsafe(models.TextChoices):
        STOP = "stop"
        LAND = "land"
        RETURN_TO_HOME = "return_to_home", "return to home"

    slug = models.SlugField(unique=True)
    name = models.CharField(max_length=100)
    description = models.TextField(blank=True)
    kind = models.CharField(
        max_length=40,
        validators=[_kind_installed],
        help_text="What kind of service this is (services.kinds): what a request sets "
        "going, what the user and the vehicles get.",
    )
    is_active = models.BooleanField(default=True)
    allowed_commands = models.JSONField(
        default=list,
        blank=True,
        help_text="Command names the user may send; empty = none (view only).",
    )
    # Limits signed into every vehicle task of this service.
    # Limits are positive or absent (null: no limit): a zero limit cannot be signed.
    max_altitude_m = models.FloatField(null=True, blank=True, validators=[MinValueValidator(0.1)])
    geofence_radius_m = models.FloatField(null=True, blank=True, validators=[MinValueValidator(1)])
    max_speed_mps = models.FloatField(null=True, blank=True, validators=[MinValueValidator(0.01)])
    link_loss_timeout_ms = models.PositiveIntegerField(
        default=500, validators=[MinValueValidator(50), MaxValueValidator(60_000)]
    )
    failsafe_action = models.CharField(
        max_length=20, choices=Failsafe.choices, default=Failsafe.STOP
    )
    session_time_limit_s = models.PositiveIntegerField(null=True, blank=True)
    max_sessions_per_user = models.PositiveIntegerField(
        default=1,
        validators=[MinValueValidator(1)],
        help_text="Live sessions one user may hold at once: a client cannot reserve the "
        "whole fleet.",
    )
    latency_soft_ms = models.PositiveIntegerField(
        null=True, blank=True, help_text="Round trip above which the agent lowers the speed."
    )
    latency_hard_ms = models.PositiveIntegerField(
        null=True, blank=True, help_text="Round trip above which only stop/land/RTL pass."
    )

    class Meta:
        ordering = ["name"]

    def __str__(self) -> str:
        return self.name

    @property
    def mode(self) -> str:
        """``sync`` when a user drives the session live, else ``async`` (its kind's)."""
        try:
            return "sync" if kind_named(self.kind).user_drives else "async"
        except UnknownKind:
            return "async"

    def clean(self) -> None:
        if (
            self.latency_soft_ms is not None
            and self.latency_hard_ms is not None
            and self.latency_soft_ms >= self.latency_hard_ms
        ):
            raise ValidationError({"latency_hard_ms": "must be above latency_soft_ms"})
        if not isinstance(self.allowed_commands, list) or not all(
            isinstance(c, str) for c in self.allowed_commands
        ):
            raise ValidationError({"allowed_commands": "must be a list of command names"})


def _min_attributes_clean(value: Any) -> None:
    if not isinstance(value, dict):
        raise ValidationError("min_attributes: must be an object of attribute: minimum")
    for name, minimum in value.items():
        spec = ATTRIBUTES.get(name)
        if not isinstance(spec, NumberAttribute):
            raise ValidationError(f"min_attributes: {name} is not a numeric attribute")
        spec.clean(minimum)


class ServiceRole(models.Model):
    """One vehicle a service needs, and the constraints that vehicle must meet."""

    class Selection(models.TextChoices):
        NEAREST = "nearest", "nearest first"
        FASTEST = "fastest", "first to arrive (distance over speed)"

    service = models.ForeignKey(Service, on_delete=models.CASCADE, related_name="roles")
    name = models.SlugField(max_length=40, help_text="e.g. vehicle, search, delivery")
    kinds = models.JSONField(
        default=list,
        blank=True,
        validators=[ChoiceListValidator("kinds", tuple(VehicleType.Kind.values))],
        help_text="Acceptable kinds; empty = any.",
    )
    adapters = models.JSONField(
        default=list,
        blank=True,
        validators=[ChoiceListValidator("adapters", tuple(VehicleType.Adapter.values))],
        help_text="Acceptable adapters; empty = any.",
    )
    cameras = models.JSONField(
        default=list,
        blank=True,
        validators=[ChoiceListValidator("cameras", CAMERAS)],
        help_text="Cameras the vehicle must all have.",
    )
    environments = models.JSONField(
        default=list,
        blank=True,
        validators=[ChoiceListValidator("environments", ENVIRONMENTS)],
        help_text="The vehicle must operate in at least one of these; empty = any.",
    )
    features = models.JSONField(
        default=list, blank=True, validators=[ChoiceListValidator("features", FEATURES)]
    )
    min_attributes = models.JSONField(
        default=dict,
        blank=True,
        validators=[_min_attributes_clean],
        help_text='Minimums, e.g. {"max_payload_kg": 1.5, "endurance_min": 20}.',
    )
    min_battery = models.FloatField(
        default=30, validators=[MinValueValidator(0), MaxValueValidator(100)]
    )
    selection = models.CharField(
        max_length=10, choices=Selection.choices, default=Selection.NEAREST
    )
    required = models.BooleanField(
        default=True,
        help_text="Assigned when the session is requested. Unrequired roles are assigned "
        "later by the workflow (e.g. a vehicle chosen once something is found).",
    )

    class Meta:
        constraints = [
            models.UniqueConstraint(fields=["service", "name"], name="unique_role_per_service")
        ]
        ordering = ["service", "pk"]

    def __str__(self) -> str:
        return f"{self.service.slug}:{self.name}"


class ServiceGrant(models.Model):
    """Who may use a service: one user or one group (roles are groups)."""

    service = models.ForeignKey(Service, on_delete=models.CASCADE, related_name="grants")
    user = models.ForeignKey(
        settings.AUTH_USER_MODEL, null=True, blank=True, on_delete=models.CASCADE
    )
    group = models.ForeignKey(Group, null=True, blank=True, on_delete=models.CASCADE)

    class Meta:
        constraints = [
            models.CheckConstraint(
                condition=(Q(user__isnull=False) & Q(group__isnull=True))
                | (Q(user__isnull=True) & Q(group__isnull=False)),
                name="grant_to_user_xor_group",
            ),
            models.UniqueConstraint(fields=["service", "user"], name="unique_user_grant"),
            models.UniqueConstraint(fields=["service", "group"], name="unique_group_grant"),
        ]

    def __str__(self) -> str:
        return f"{self.service.slug} → {self.user or self.group}"


class Session(models.Model):
    """One use of a service by one user; see services.sessions.states for the state machine."""

    class State(models.TextChoices):
        REQUESTED = "requested"
        ASSIGNED = "assigned"
        ACTIVE = "active"
        ENDED = "ended"
        FAILED = "failed"
        ABORTED = "aborted"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    service = models.ForeignKey(Service, on_delete=models.PROTECT, related_name="sessions")
    user = models.ForeignKey(
        settings.AUTH_USER_MODEL, on_delete=models.PROTECT, related_name="iouv_sessions"
    )
    state = models.CharField(max_length=10, choices=State.choices, default=State.REQUESTED)
    reason = models.CharField(max_length=300, blank=True)
    target_lat = models.FloatField(
        null=True, blank=True, validators=[MinValueValidator(-90), MaxValueValidator(90)]
    )
    target_lon = models.FloatField(
        null=True, blank=True, validators=[MinValueValidator(-180), MaxValueValidator(180)]
    )
    params = models.JSONField(default=dict, blank=True)
    relay = models.BooleanField(
        default=False, help_text="Control goes through the platform instead of point-to-point."
    )

    class ControlPath(models.TextChoices):
        WEBRTC_DIRECT = "webrtc_direct", "WebRTC, direct"
        WEBRTC_TURN = "webrtc_turn", "WebRTC through TURN"
        RELAY = "relay", "relay through the platform"
        WEBSOCKET = "websocket", "direct WebSocket"

    control_path = models.CharField(
        max_length=16,
        choices=ControlPath.choices,
        blank=True,
        help_text="How the controller's messages reach the vehicle, as its agent last said.",
    )
    created_at = models.DateTimeField(auto_now_add=True)
    assigned_at = models.DateTimeField(null=True, blank=True)
    started_at = models.DateTimeField(null=True, blank=True)
    ended_at = models.DateTimeField(null=True, blank=True)

    # Not columns. Left on the instance by the function that just wrote them, under the
    # session's lock, so that an answer about the session does not read them back
    # (services.web.api_schemas): all its assignments with their vehicles, its whole log
    # in order, and what its end sent the vehicles (services.sessions.selectors.session_delivery),
    # as that transaction left them. None: not known, read them.
    known_assignments: list[Assignment] | None = None
    known_events: list[SessionEvent] | None = None
    known_delivery: list[dict[str, Any]] | None = None

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["state"])]
        permissions = [
            ("use_services", "Can request services"),
            ("stop_session", "Can stop any session"),
        ]

    def __str__(self) -> str:
        return f"{self.service.slug} for {self.user} ({self.state})"

    @property
    def target(self) -> tuple[float, float] | None:
        if self.target_lat is None or self.target_lon is None:
            return None
        return (self.target_lat, self.target_lon)


class Assignment(models.Model):
    """A vehicle holding a role in a session. At most one active row per vehicle,
    enforced by the database, so no vehicle is ever held twice."""

    session = models.ForeignKey(Session, on_delete=models.CASCADE, related_name="assignments")
    role = models.CharField(max_length=40)
    vehicle = models.ForeignKey(Vehicle, on_delete=models.PROTECT, related_name="assignments")
    active = models.BooleanField(default=True)
    distance_m = models.FloatField(help_text="From the vehicle to the target when assigned.")
    created_at = models.DateTimeField(auto_now_add=True)
    released_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        constraints = [
            models.UniqueConstraint(
                fields=["vehicle"], condition=Q(active=True), name="one_active_assignment"
            ),
        ]
        ordering = ["created_at"]

    def __str__(self) -> str:
        return f"{self.vehicle} as {self.role}"


class SessionEvent(models.Model):
    """Append-only, hash-chained session log (see services.sessions.log)."""

    session = models.ForeignKey(Session, on_delete=models.PROTECT, related_name="events")
    seq = models.PositiveIntegerField()
    kind = models.CharField(max_length=40)
    data = models.JSONField(default=dict, blank=True)
    #: When it was written.
    created_at = models.DateTimeField()
    #: When it happened on the vehicle, by the vehicle's clock, for an event logged from
    #: an agent's report (null for the platform's own): a report sent while the platform
    #: or its database was away is written late.
    occurred_at = models.DateTimeField(null=True, blank=True)
    prev_hash = models.CharField(max_length=64)
    hash = models.CharField(max_length=64)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["session", "seq"], name="unique_event_seq")]
        ordering = ["session", "seq"]

    def __str__(self) -> str:
        return f"#{self.seq} {self.kind}"

    def save(self, *args: Any, **kwargs: Any) -> None:
        # The log is append-only: refuse to rewrite a stored event through the ORM.
        if not self._state.adding:
            raise ValidationError("session events are append-only")
        super().save(*args, **kwargs)

    def delete(self, *args: Any, **kwargs: Any) -> Any:
        raise ValidationError("session events are append-only")


class Notice(models.Model):
    """One message to people outside the session (a team to alert, a recipient, the
    monitors' dashboard) about one moment of a session, on one channel:
    sent until it succeeds, once (services.sessions.notices)."""

    class Channel(models.TextChoices):
        EMAIL = "email"
        WEBHOOK = "webhook"
        DASHBOARD = "dashboard", "monitors' dashboard"

    class Level(models.TextChoices):
        INFO = "info"
        WARN = "warn", "warning"
        BAD = "bad", "alert"

    session = models.ForeignKey(Session, on_delete=models.CASCADE, related_name="notices")
    channel = models.CharField(max_length=10, choices=Channel.choices)
    #: What it is about, one per session and channel, named by the kind.
    topic = models.SlugField(max_length=40)
    #: The e-mail address or webhook URL ("" for the dashboard).
    target = models.CharField(max_length=300, blank=True)
    level = models.CharField(max_length=5, choices=Level.choices, default=Level.INFO)
    subject = models.CharField(max_length=200, blank=True)
    message = models.TextField()
    #: The webhook's JSON body (the message and the facts a program needs).
    payload = models.JSONField(default=dict, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    sent_at = models.DateTimeField(null=True, blank=True)
    attempts = models.PositiveIntegerField(default=0)
    #: A worker sending this notice holds it until then; after that (the worker died
    #: mid-send), another may send it again, with the same idempotency key.
    claimed_until = models.DateTimeField(null=True, blank=True)
    last_error = models.CharField(max_length=300, blank=True)

    class Meta:
        constraints = [
            models.UniqueConstraint(
                fields=["session", "channel", "topic"], name="one_notice_per_topic"
            )
        ]
        ordering = ["created_at"]

    def __str__(self) -> str:
        return f"{self.topic} by {self.channel} for {self.session_id}"


class RecordBatch(models.Model):
    """One batch of a session's flight record as a vehicle's agent uploaded it
    (services.records.keeping): samples ``first`` .. ``last``, their SHA-256 (``digest``, which
    the session's hash-chained log holds too). Stored once per (session, vehicle,
    first): a batch the agent sends again is acknowledged, not stored twice."""

    session = models.ForeignKey(Session, on_delete=models.CASCADE, related_name="record_batches")
    vehicle = models.ForeignKey(Vehicle, on_delete=models.PROTECT, related_name="record_batches")
    first = models.PositiveIntegerField()
    last = models.PositiveIntegerField()
    digest = models.CharField(max_length=64)
    received_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        constraints = [
            models.UniqueConstraint(
                fields=["session", "vehicle", "first"], name="unique_record_batch"
            )
        ]
        ordering = ["session", "vehicle", "first"]

    def __str__(self) -> str:
        return f"record {self.first}-{self.last} of {self.vehicle_id}"


class RecordSample(models.Model):
    """One numbered sample of a flight record (agents.recording): ``t`` is Unix seconds
    by the vehicle's clock, ``kind`` telemetry, command, event, tlog or dropped."""

    batch = models.ForeignKey(RecordBatch, on_delete=models.CASCADE, related_name="samples")
    session = models.ForeignKey(Session, on_delete=models.CASCADE, related_name="record_samples")
    vehicle = models.ForeignKey(Vehicle, on_delete=models.PROTECT, related_name="+")
    seq = models.PositiveIntegerField()
    t = models.FloatField()
    kind = models.CharField(max_length=12)
    data = models.JSONField(default=dict)

    class Meta:
        constraints = [
            models.UniqueConstraint(
                fields=["session", "vehicle", "seq"], name="unique_record_sample"
            )
        ]
        ordering = ["session", "vehicle", "seq"]

    def __str__(self) -> str:
        return f"#{self.seq} {self.kind}"


class SessionArtifact(models.Model):
    """A file a vehicle's mission made in a session and uploaded (``artifact`` chunks,
    services.records.artifacts): a photo, with ``meta`` saying what it is
    (where it was taken). One per (session, name); ``data`` is there once every chunk
    is and their SHA-256 is ``sha256`` (``stored_at`` set), and only its name, size and
    digest go into the session's hash-chained log."""

    session = models.ForeignKey(Session, on_delete=models.CASCADE, related_name="artifacts")
    vehicle = models.ForeignKey(Vehicle, on_delete=models.PROTECT, related_name="+")
    name = models.CharField(max_length=100)
    media_type = models.CharField(max_length=80)
    size = models.PositiveIntegerField()
    sha256 = models.CharField(max_length=64)
    count = models.PositiveIntegerField()
    meta = models.JSONField(default=dict)
    data = models.BinaryField(null=True, blank=True)
    received_at = models.DateTimeField(auto_now_add=True)
    stored_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        constraints = [
            models.UniqueConstraint(fields=["session", "name"], name="unique_session_artifact")
        ]
        ordering = ["session", "received_at", "name"]

    def __str__(self) -> str:
        return f"{self.name} of {self.session_id}"

    @property
    def stored(self) -> bool:
        return self.stored_at is not None


class ArtifactChunk(models.Model):
    """A chunk of a :class:`SessionArtifact` not yet whole (deleted once it is)."""

    artifact = models.ForeignKey(SessionArtifact, on_delete=models.CASCADE, related_name="chunks")
    index = models.PositiveIntegerField()
    data = models.BinaryField()

    class Meta:
        constraints = [
            models.UniqueConstraint(fields=["artifact", "index"], name="unique_artifact_chunk")
        ]

    def __str__(self) -> str:
        return f"chunk {self.index} of {self.artifact_id}"
