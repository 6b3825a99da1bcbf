"""The demo world: the paper's fleet near Aveiro, its services and one user per role.

``demo_seed`` is idempotent: every row is keyed by its name, slug or username and
updated in place, so running it again changes nothing structurally. Live vehicle state
(status, position, battery) is left alone on a re-run, so seeding while the simulated
fleet is connected does not knock it offline.

Positions: the land station is on the university campus; the coastal station is on
Costa Nova beach, with the sea to its WEST (east of it is the lagoon and land).
"""

from __future__ import annotations

import json
import os
import secrets
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group
from django.db import transaction

from accounts.roles import ADMIN, CLIENT, MONITOR, OPERATOR, roles_ensure, user_set_roles
from agents.geo import offset
from agents.vehicles.registry import integration
from fleet.attributes import attributes_clean, camera_optics
from fleet.credentials import vehicle_issue_credential
from fleet.models import Station, Vehicle, VehicleType
from services.kinds import DemoService, kinds
from services.models import Service, ServiceGrant, ServiceRole
from services.sessions.signing import platform_public_key_pem

DEFAULT_PLATFORM_URL = "ws://127.0.0.1:8000"


def site_url(platform_url: str) -> str:
    """The portal's address for the agents' ``platform_url`` (same host and port)."""
    for socket_scheme, web_scheme in (("wss://", "https://"), ("ws://", "http://")):
        if platform_url.startswith(socket_scheme):
            return web_scheme + platform_url[len(socket_scheme) :].rstrip("/")
    return platform_url.rstrip("/")


# --------------------------------------------------------------------------------------
# Stations
# --------------------------------------------------------------------------------------

CAMPUS = "Campus station"
COSTA_NOVA = "Costa Nova station"

#: Where the simulated person in the water is, about 900 m off Costa Nova's beach: a
#: search whose area covers this point finds them (``bin/demo --rescue`` asks for one).
CASTAWAY = (40.6441, -8.7561)

STATIONS: dict[str, dict[str, Any]] = {
    CAMPUS: {"lat": 40.6306, "lon": -8.6588, "environments": ["land", "air"]},
    COSTA_NOVA: {"lat": 40.6443, "lon": -8.7455, "environments": ["sea", "air"]},
}

# --------------------------------------------------------------------------------------
# Command vocabularies (the wire protocol's declaration format, see agents.protocol)
# --------------------------------------------------------------------------------------


# The vocabularies are read from the adapters themselves, so the platform's declared
# commands and the service grants always name what the agents really accept. Building
# an adapter only checks its options; nothing is opened.
PAYLOAD_OPTIONS: dict[str, Any] = {"payload": {"method": "gripper"}}


def _declared(adapter: str, options: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
    return [c.to_profile() for c in integration(adapter).commands(dict(options or {}))]


CAR_COMMANDS = _declared("car", {"camera_arm": True, "distance_sensor": True})
QUADCOPTER_COMMANDS = _declared("mavlink")
VTOL_COMMANDS = _declared("spektrum")
RESCUE_DRONE_COMMANDS = _declared("mavlink", PAYLOAD_OPTIONS)
#: ArduPilot Rover with its boat frame, on the same MAVLink integration.
BOAT_OPTIONS: dict[str, Any] = {"vehicle_class": "boat"}
BOAT_COMMANDS = _declared("mavlink", {**BOAT_OPTIONS, **PAYLOAD_OPTIONS})


def command_names(commands: list[dict[str, Any]]) -> list[str]:
    """The names in a command vocabulary, in declaration order."""
    return [c["name"] for c in commands]


# --------------------------------------------------------------------------------------
# Vehicle types and vehicles
# --------------------------------------------------------------------------------------

CAR = "Raspberry Pi car"
QUADCOPTER = "MAVLink quadcopter"
VTOL = "Spektrum VTOL plane"
RESCUE_DRONE = "Rescue payload drone"
BOAT = "MAVLink boat"

K = VehicleType.Kind
A = VehicleType.Adapter

VEHICLE_TYPES: dict[str, dict[str, Any]] = {
    CAR: {
        "kind": K.GROUND,
        "adapter": A.CAR,
        "description": "Raspberry Pi robot car with a pan/tilt camera, driven through gpiozero.",
        "commands": CAR_COMMANDS,
    },
    QUADCOPTER: {
        "kind": K.AERIAL,
        "adapter": A.MAVLINK,
        "description": "Multicopter with a MAVLink autopilot (ArduPilot/PX4).",
        "commands": QUADCOPTER_COMMANDS,
    },
    VTOL: {
        "kind": K.HYBRID,
        "adapter": A.SPEKTRUM,
        "description": "VTOL plane flown through a Spektrum receiver on a serial port.",
        "commands": VTOL_COMMANDS,
    },
    RESCUE_DRONE: {
        "kind": K.AERIAL,
        "adapter": A.MAVLINK,
        "description": "MAVLink multicopter carrying a releasable rescue buoy.",
        "commands": RESCUE_DRONE_COMMANDS,
    },
    BOAT: {
        "kind": K.AQUATIC,
        "adapter": A.MAVLINK,
        "description": "Surface boat with an ArduPilot Rover autopilot and a release hook.",
        "commands": BOAT_COMMANDS,
    },
}
#: Adapter options a vehicle type's agents start with, besides those derived from
#: each vehicle's attributes (see vehicle_agent_config).
TYPE_OPTIONS: dict[str, dict[str, Any]] = {BOAT: BOAT_OPTIONS}


def _car(features: list[str]) -> dict[str, Any]:
    return {
        "vehicle_type": CAR,
        "station": CAMPUS,
        "attributes": {
            "endurance_min": 60,
            "max_range_m": 2000,
            "max_altitude_m": 0,
            "max_speed_mps": 1.5,
            "max_payload_kg": 0.5,
            "cameras": ["rgb"],
            "camera_range_m": 20,
            "environments": ["land"],
            "features": features,
        },
    }


VEHICLES: dict[str, dict[str, Any]] = {
    "car-1": _car(["camera_arm", "obstacle_sensor"]),
    "car-2": _car([]),
    "car-3": _car([]),
    "car-4": _car([]),
    "quad-1": {
        "vehicle_type": QUADCOPTER,
        "station": CAMPUS,
        "attributes": {
            "endurance_min": 20,
            "max_range_m": 5000,
            "max_altitude_m": 120,
            "max_speed_mps": 12,
            "max_payload_kg": 0.5,
            "cameras": ["rgb"],
            "camera_range_m": 100,
            # A downward-looking mapping camera: 4:3, 1024 px across a 73.7° field.
            "camera_hfov_deg": 73.7,
            "camera_width_px": 1024,
            "camera_height_px": 768,
            "environments": ["air", "land"],
            "features": ["gps"],
        },
    },
    "vtol-1": {
        "vehicle_type": VTOL,
        "station": CAMPUS,
        "attributes": {
            "endurance_min": 30,
            "max_range_m": 20000,
            "max_altitude_m": 120,
            "max_speed_mps": 20,
            "max_payload_kg": 0,
            "cameras": ["rgb"],
            "camera_range_m": 100,
            "environments": ["air", "land", "sea"],
            "features": ["gps"],
        },
    },
    "search-1": {
        "vehicle_type": QUADCOPTER,
        "station": COSTA_NOVA,
        "attributes": {
            "endurance_min": 30,
            "max_range_m": 8000,
            "max_altitude_m": 120,
            "max_speed_mps": 15,
            "max_payload_kg": 0.5,
            "cameras": ["rgb", "thermal"],
            "camera_range_m": 120,
            "environments": ["air", "sea", "land"],
            "features": ["gps"],
        },
    },
    "lifeguard-1": {
        "vehicle_type": RESCUE_DRONE,
        "station": COSTA_NOVA,
        "attributes": {
            "endurance_min": 25,
            "max_range_m": 6000,
            "max_altitude_m": 120,
            "max_speed_mps": 15,
            "max_payload_kg": 2.0,
            "cameras": ["rgb"],
            "camera_range_m": 100,
            "environments": ["air", "sea"],
            "features": ["payload_release", "gps"],
        },
    },
    "boat-1": {
        "vehicle_type": BOAT,
        # Launched from the beach at the station, like the lifeguards' own boats; the
        # sea is to the west.
        "station": COSTA_NOVA,
        "attributes": {
            "endurance_min": 120,
            "max_range_m": 15000,
            "max_altitude_m": 0,
            "max_speed_mps": 4,
            "max_payload_kg": 20,
            "cameras": ["rgb"],
            "camera_range_m": 50,
            "environments": ["sea"],
            "features": ["payload_release", "gps"],
        },
    },
}

# --------------------------------------------------------------------------------------
# Services: each kind offers its own (ServiceKind.demo_services)
# --------------------------------------------------------------------------------------


def demo_services() -> dict[str, DemoService]:
    """Every installed kind's demo services, by slug, with their ``kind`` filled in."""
    services: dict[str, DemoService] = {}
    for kind in kinds():
        for slug, spec in kind.demo_services().items():
            if slug in services:
                raise ValueError(f"demo service {slug!r} is offered by two kinds")
            services[slug] = DemoService(
                fields={**spec.fields, "kind": kind.name}, roles=spec.roles
            )
    return services


# Role fields reset to their defaults when a demo role does not mention them, so an
# edit made in the admin does not survive a re-seed half-applied.
_ROLE_DEFAULTS: dict[str, Any] = {
    "kinds": [],
    "adapters": [],
    "cameras": [],
    "environments": [],
    "features": [],
    "min_attributes": {},
    "min_battery": 30,
    "selection": ServiceRole.Selection.NEAREST,
    "required": True,
}
_SERVICE_DEFAULTS: dict[str, Any] = {
    "is_active": True,
    "max_altitude_m": None,
    "geofence_radius_m": None,
    "max_speed_mps": None,
    "session_time_limit_s": None,
    "latency_soft_ms": None,
    "latency_hard_ms": None,
}

# --------------------------------------------------------------------------------------
# Users
# --------------------------------------------------------------------------------------

USERS: dict[str, tuple[str, ...]] = {
    "client": (CLIENT,),
    # A second client, to watch the first one's vehicle while it drives.
    "client2": (CLIENT,),
    "monitor": (MONITOR,),
    "operator": (OPERATOR,),
    "admin": (ADMIN,),
}

# --------------------------------------------------------------------------------------
# Seeding
# --------------------------------------------------------------------------------------


@dataclass
class DemoSeed:
    """What a seed run produced: the users' passwords and the agent configs written."""

    passwords: dict[str, str] = field(default_factory=dict)
    roles: dict[str, tuple[str, ...]] = field(default_factory=dict)
    config_paths: list[Path] = field(default_factory=list)


def stations_seed() -> dict[str, Station]:
    """Create or update the demo stations, by name."""
    return {
        name: Station.objects.update_or_create(name=name, defaults=values)[0]
        for name, values in STATIONS.items()
    }


def vehicle_types_seed() -> dict[str, VehicleType]:
    """Create or update the demo vehicle types and their command vocabularies, by name."""
    return {
        name: VehicleType.objects.update_or_create(name=name, defaults=values)[0]
        for name, values in VEHICLE_TYPES.items()
    }


def vehicles_seed(
    *, stations: Mapping[str, Station], types: Mapping[str, VehicleType]
) -> dict[str, Vehicle]:
    """Create or update the demo vehicles, by name.

    Only declared fields are written: status, position and battery belong to the
    uplink, and a new vehicle starts offline until its agent connects.
    """
    vehicles = {}
    for name, spec in VEHICLES.items():
        vehicle, _ = Vehicle.objects.update_or_create(
            name=name,
            defaults={
                "vehicle_type": types[spec["vehicle_type"]],
                "station": stations[spec["station"]],
                # Fails loudly if the demo data itself is wrong.
                "attributes": attributes_clean(spec["attributes"]),
            },
        )
        vehicles[name] = vehicle
    return vehicles


def services_seed(*, client_group: Group) -> dict[str, Service]:
    """Create or update every kind's demo services (after the kinds' own demo rows),
    their roles and their grant to ``client_group``.

    The demo services are owned by the seed: roles not in the definition are removed.
    """
    for kind in kinds():
        kind.demo_seed()
    services = {}
    for slug, spec in demo_services().items():
        service, _ = Service.objects.update_or_create(
            slug=slug, defaults={**_SERVICE_DEFAULTS, **spec.fields}
        )
        for role_name, role_fields in spec.roles.items():
            ServiceRole.objects.update_or_create(
                service=service, name=role_name, defaults={**_ROLE_DEFAULTS, **role_fields}
            )
        service.roles.exclude(name__in=list(spec.roles)).delete()
        ServiceGrant.objects.get_or_create(service=service, group=client_group)
        services[slug] = service
    return services


def users_seed(*, password: str | None = None) -> dict[str, str]:
    """Create or update one user per role; returns username -> the password just set.

    Without ``password`` each user gets a fresh random one on every run, so no demo
    password is ever fixed in the code.
    """
    User = get_user_model()
    passwords = {}
    for username, roles in USERS.items():
        user, _ = User.objects.get_or_create(username=username)
        secret = password if password is not None else secrets.token_urlsafe(9)
        user.set_password(secret)
        user.save(update_fields=["password"])
        user_set_roles(user=user, roles=roles)
        passwords[username] = secret
    return passwords


def vehicle_agent_config(
    *, vehicle: Vehicle, credential: str, platform_url: str = DEFAULT_PLATFORM_URL
) -> dict[str, Any]:
    """The JSON config a vehicle agent starts from (see agents.config).

    Holds the platform's public key, so the agent can check signed tasks and grants
    offline, and adapter options derived from the declared attributes: the simulated
    vehicle starts at its station, a few metres from its neighbours.
    """
    attrs = vehicle.attributes
    index = sum(1 for _ in vehicle.station.vehicles.filter(name__lt=vehicle.name))
    origin = offset((vehicle.station.lat, vehicle.station.lon), 0.0, 3.0 * index)
    options: dict[str, Any] = {
        **TYPE_OPTIONS.get(vehicle.vehicle_type.name, {}),
        "origin": [round(origin[0], 7), round(origin[1], 7)],
        "vehicle_type": vehicle.vehicle_type.name,
    }
    if "payload_release" in vehicle.features:
        options.update(PAYLOAD_OPTIONS)
    if vehicle.vehicle_type.adapter == VehicleType.Adapter.MAVLINK:
        options["max_speed_mps"] = attrs.get("max_speed_mps", 10)
        if vehicle.vehicle_type.kind != VehicleType.Kind.AQUATIC:
            options["max_takeoff_m"] = attrs.get("max_altitude_m", 120)
    if vehicle.vehicle_type.adapter == VehicleType.Adapter.CAR:
        options["camera_arm"] = "camera_arm" in vehicle.features
        options["distance_sensor"] = "obstacle_sensor" in vehicle.features
        options["max_speed_mps"] = attrs.get("max_speed_mps", 0.5)
    thermal = None
    video: dict[str, Any] | None = None
    if vehicle.cameras:
        # A vehicle that works only on the water sees the sea, not grass and hills.
        environments = set(attrs.get("environments") or [])
        video = {"source": "synthetic", "scene": "sea" if environments == {"sea"} else "land"}
    optics = camera_optics(attrs)
    photo = None
    if optics is not None:
        # The camera missions photograph with: in the demo, a simulated one looking
        # straight down at a ground that is the same wherever it is seen from.
        photo = {
            "source": "nadir",
            "hfov_deg": optics.hfov_deg,
            "width": optics.width_px,
            "height": optics.height_px,
        }
    if "thermal" in vehicle.cameras:
        # The simulated sea holds the demo's castaway, so a search over it finds them;
        # the user watches the thermal view.
        thermal = {"source": "synthetic", "hfov_deg": 57, "persons": [list(CASTAWAY)]}
        video = {"source": "thermal"}
    return {
        "platform_url": platform_url,
        "platform_public_key": platform_public_key_pem(),
        "vehicle_id": str(vehicle.pk),
        "vehicle_name": vehicle.name,
        "credential": credential,
        "adapter": vehicle.vehicle_type.adapter,
        "adapter_options": options,
        "video": video,
        "thermal": thermal,
        "photo": photo,
        "vehicle_type": vehicle.vehicle_type.name,
    }


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by the owner only, replacing it atomically.

    The file is created 0600 from the start (never world-readable, not even briefly)
    and renamed into place, so an agent never reads a half-written credential.
    """
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def agent_configs_write(
    *, vehicles: Mapping[str, Vehicle], directory: Path, platform_url: str = DEFAULT_PLATFORM_URL
) -> list[Path]:
    """Issue a fresh credential for each vehicle and write ``<name>.json`` into ``directory``.

    Each vehicle's previous credential stops working. Returns the paths written.
    """
    if not platform_url.startswith(("ws://", "wss://")):
        raise ValueError(f"platform_url must be a ws:// or wss:// URL, got {platform_url!r}")
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    paths = []
    for name, vehicle in vehicles.items():
        credential = vehicle_issue_credential(vehicle=vehicle)
        config = vehicle_agent_config(
            vehicle=vehicle, credential=credential, platform_url=platform_url
        )
        path = directory / f"{name}.json"
        _write_private(path, json.dumps(config, indent=2) + "\n")
        paths.append(path)
    return paths


def demo_seed(
    *,
    password: str | None = None,
    credentials_dir: Path | None = None,
    platform_url: str = DEFAULT_PLATFORM_URL,
) -> DemoSeed:
    """Create or update the whole demo world; see the module docstring.

    ``password`` sets every demo user's password (else each gets a random one).
    ``credentials_dir`` also issues a fresh credential to every demo vehicle and writes
    its agent config there; without it existing credentials are left alone.
    """
    if credentials_dir is not None and not platform_url.startswith(("ws://", "wss://")):
        # Checked before anything is written.
        raise ValueError(f"platform_url must be a ws:// or wss:// URL, got {platform_url!r}")
    with transaction.atomic():
        groups = roles_ensure()
        stations = stations_seed()
        types = vehicle_types_seed()
        vehicles = vehicles_seed(stations=stations, types=types)
        services_seed(client_group=groups[CLIENT])
        passwords = users_seed(password=password)
    result = DemoSeed(passwords=passwords, roles=dict(USERS))
    if credentials_dir is not None:
        # After the commit: a config file must never hold a credential whose digest was
        # rolled back.
        result.config_paths = agent_configs_write(
            vehicles=vehicles, directory=Path(credentials_dir), platform_url=platform_url
        )
    return result
