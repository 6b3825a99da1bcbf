"""Fleet rows: stations, vehicle types and vehicles."""

from __future__ import annotations

import uuid

from django.core.exceptions import ValidationError
from django.core.validators import MaxValueValidator, MinValueValidator
from django.db import models

from fleet.attributes import (
    ENVIRONMENTS,
    ChoiceListValidator,
    DeclaredAttributes,
    attributes_clean,
)


class Station(models.Model):
    """A base where vehicles are kept, launched and returned."""

    name = models.CharField(max_length=100, unique=True)
    lat = models.FloatField(validators=[MinValueValidator(-90), MaxValueValidator(90)])
    lon = models.FloatField(validators=[MinValueValidator(-180), MaxValueValidator(180)])
    environments = models.JSONField(
        default=list,
        validators=[ChoiceListValidator("environments", ENVIRONMENTS)],
        help_text="Any of land, sea, air.",
    )

    class Meta:
        ordering = ["name"]

    def __str__(self) -> str:
        return self.name


class VehicleType(models.Model):
    """A model of vehicle: its kind, the adapter that drives it and its commands."""

    class Kind(models.TextChoices):
        GROUND = "ground"
        AERIAL = "aerial"
        AQUATIC = "aquatic"
        HYBRID = "hybrid"

    class Adapter(models.TextChoices):
        CAR = "car", "Raspberry Pi car (gpiozero)"
        MAVLINK = "mavlink", "MAVLink autopilot (pymavlink)"
        SPEKTRUM = "spektrum", "Spektrum receiver (serial)"

    name = models.CharField(max_length=100, unique=True)
    kind = models.CharField(max_length=10, choices=Kind.choices)
    adapter = models.CharField(max_length=10, choices=Adapter.choices)
    description = models.TextField(blank=True)
    commands = models.JSONField(
        default=list,
        blank=True,
        help_text="Declared command vocabulary; the agent reports the authoritative one.",
    )

    class Meta:
        ordering = ["name"]

    def __str__(self) -> str:
        return self.name


class Vehicle(DeclaredAttributes, models.Model):
    """One vehicle, its declared attributes and what its agent last reported."""

    class Status(models.TextChoices):
        OFFLINE = "offline"
        IDLE = "idle"
        RESERVED = "reserved"
        IN_SERVICE = "in_service", "in service"
        RETURNING = "returning"
        # Its session is over but the agent has not yet confirmed the end (or revoke):
        # not assignable, whatever its heartbeats say (see fleet.outbox).
        RELEASING = "releasing", "finishing its task"
        FAILSAFE = "failsafe"
        MAINTENANCE = "maintenance"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    name = models.CharField(max_length=100, unique=True)
    vehicle_type = models.ForeignKey(VehicleType, on_delete=models.PROTECT, related_name="vehicles")
    station = models.ForeignKey(Station, on_delete=models.PROTECT, related_name="vehicles")
    attributes = models.JSONField(
        default=dict,
        help_text="Declared attributes with units (see fleet.attributes), and features.",
    )

    # Enrolment: the agent's credential, kept as a SHA-256 digest (see fleet.credentials).
    credential_hash = models.CharField(max_length=64, blank=True, editable=False)
    #: Bumped by every credential issued: an uplink authenticated under an older one is
    #: closed (see fleet.outbox).
    credential_generation = models.PositiveIntegerField(default=0, editable=False)
    credential_issued_at = models.DateTimeField(null=True, blank=True, editable=False)

    # Live state, written by the uplink.
    status = models.CharField(max_length=12, choices=Status.choices, default=Status.OFFLINE)
    maintenance = models.BooleanField(
        default=False, help_text="Out of service: never assigned, whatever the agent says."
    )
    last_seen = models.DateTimeField(null=True, blank=True)
    #: The platform process that holds (or last held) the agent's uplink: while that
    #: process is gone, the vehicle's silence is the platform's (fleet.servers).
    uplink_server = models.UUIDField(null=True, blank=True, editable=False)
    control_url = models.CharField(max_length=300, blank=True)
    profile = models.JSONField(default=dict, blank=True, editable=False)
    lat = models.FloatField(null=True, blank=True)
    lon = models.FloatField(null=True, blank=True)
    alt = models.FloatField(null=True, blank=True)
    battery = models.FloatField(
        null=True, blank=True, validators=[MinValueValidator(0), MaxValueValidator(100)]
    )

    class Meta:
        ordering = ["station__name", "name"]
        indexes = [models.Index(fields=["status"])]
        permissions = [
            ("view_fleet", "Can watch the live fleet"),
            ("set_maintenance", "Can put vehicles in and out of service"),
            ("issue_credential", "Can issue a vehicle's agent credential"),
        ]

    def __str__(self) -> str:
        return self.name

    def clean(self) -> None:
        try:
            self.attributes = attributes_clean(self.attributes)
        except ValidationError as exc:
            raise ValidationError({"attributes": exc.messages}) from None

    @property
    def position(self) -> tuple[float, float]:
        """Where the vehicle is: its reported position, else its station's."""
        if self.lat is not None and self.lon is not None:
            return (self.lat, self.lon)
        return (self.station.lat, self.station.lon)


class LayerMessage(models.Model):
    """A channel-layer group message waiting for the ASGI process (embedded mode only,
    see operations.layer): written by a worker in its own transaction, relayed and deleted."""

    group = models.CharField(max_length=100)
    message = models.JSONField()
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["pk"]

    def __str__(self) -> str:
        return f"{self.group}: {self.message.get('type', '?')}"


class AgentMessage(models.Model):
    """A message the platform owes a vehicle's agent, kept until the agent acknowledges it.

    The platform's word to a vehicle (a task, a revoke, the end of a task, the closing
    of an uplink whose credential was replaced) is written here in the transaction that
    decides it, and delivered by the process holding the vehicle's uplink (fleet.outbox),
    again and again until the agent answers ``ack`` with its ``key``. A broker outage
    delays it; nothing loses it. Messages of one vehicle are delivered in ``id`` order.
    """

    class Kind(models.TextChoices):
        TASK = "task"
        REVOKE = "revoke"
        END_TASK = "end_task"
        #: Not sent to the agent: the uplink holding an older credential is closed.
        DISCONNECT = "disconnect"

    class State(models.TextChoices):
        PENDING = "pending"
        ACKED = "acked", "acknowledged"
        #: Superseded before delivery (a task whose session ended, a reconnect that
        #: showed the agent does not need it).
        CANCELLED = "cancelled"

    id = models.BigAutoField(primary_key=True)
    #: The message id on the wire: random, so an agent's memory of ids it has handled
    #: can never match a different message.
    key = models.UUIDField(default=uuid.uuid4, unique=True, editable=False)
    vehicle = models.ForeignKey(Vehicle, on_delete=models.CASCADE, related_name="messages")
    #: The session the message is about (fleet does not know sessions: a plain id).
    session_id = models.UUIDField(null=True, blank=True)
    kind = models.CharField(max_length=12, choices=Kind.choices)
    message = models.JSONField(help_text="The uplink_to_agent message, without its id.")
    state = models.CharField(max_length=10, choices=State.choices, default=State.PENDING)
    created_at = models.DateTimeField(auto_now_add=True)
    #: When it was last put on an uplink, and how often.
    sent_at = models.DateTimeField(null=True, blank=True)
    attempts = models.PositiveIntegerField(default=0)
    acked_at = models.DateTimeField(null=True, blank=True)
    #: What the agent said when it acknowledged (``ok`` and a short detail).
    result = models.JSONField(default=dict, blank=True)

    class Meta:
        ordering = ["id"]
        indexes = [
            # The outbox reads only what is still owed, so the index holds only that.
            models.Index(
                fields=["vehicle", "id"],
                condition=models.Q(state="pending"),
                name="agent_message_pending",
            ),
            models.Index(fields=["session_id"], name="agent_message_session"),
        ]

    def __str__(self) -> str:
        return f"{self.kind} to {self.vehicle_id} ({self.state})"


class UplinkServer(models.Model):
    """A platform process that serves agent uplinks, as long as it beats: it writes
    ``alive_at`` every ``IOUV_UPLINK_SERVER_BEAT_S`` while it runs (fleet.servers).
    The supervisor's timers read these rows to tell the platform's own absence from a
    vehicle's."""

    id = models.UUIDField(primary_key=True)
    started_at = models.DateTimeField()
    alive_at = models.DateTimeField(db_index=True)
    #: Where it runs, for people reading the table: host name and process id.
    name = models.CharField(max_length=120, blank=True)

    def __str__(self) -> str:
        return self.name or str(self.pk)
