"""The demo seed: idempotent, valid data, grants, passwords and agent configs."""

from __future__ import annotations

import json
import stat
from io import StringIO
from pathlib import Path
from typing import Any

import pytest
from django.contrib.auth import authenticate, get_user_model
from django.core.management import call_command
from django.core.management.base import CommandError

from accounts.roles import user_roles
from agents.config import AgentConfig
from agents.geography import is_water
from fleet.attributes import attributes_clean
from fleet.credentials import vehicle_authenticate
from fleet.forms import commands_validate
from fleet.models import Station, Vehicle, VehicleType
from services.demo import VEHICLE_TYPES, VEHICLES, demo_seed, demo_services
from services.models import Service, ServiceGrant, ServiceRole
from services.sessions.grants import services_for_user
from services.sessions.signing import platform_public_key_pem

pytestmark = pytest.mark.django_db

#: Every installed kind's demo services (each kind offers its own:
#: ServiceKind.demo_services); a kind added in its folder adds its own.
DEMO_SLUGS = set(demo_services())
#: Those of the kinds that come with the platform.
BUILT_IN_SLUGS = {
    "drive-car",
    "fly-drone",
    "fly-vtol",
    "drive-boat",
    "spectate",
    "rescue-at-sea",
    "parcel-delivery",
}


@pytest.fixture(autouse=True)
def _fast_hasher(settings: Any) -> None:
    # Four users per seed: the default PBKDF2 would dominate the run time.
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]


def _counts() -> dict[str, int]:
    return {
        "stations": Station.objects.count(),
        "types": VehicleType.objects.count(),
        "vehicles": Vehicle.objects.count(),
        "services": Service.objects.count(),
        "roles": ServiceRole.objects.count(),
        "grants": ServiceGrant.objects.count(),
        "users": get_user_model().objects.count(),
    }


def test_seed_twice_changes_nothing_structurally() -> None:
    demo_seed(password="pw-one")
    first = _counts()
    demo_seed(password="pw-two")
    assert _counts() == first
    offered = demo_services()
    assert set(offered) >= BUILT_IN_SLUGS
    assert first == {
        "stations": 2,
        "types": 5,
        "vehicles": 9,
        "services": len(offered),  # 7 built in
        "roles": sum(len(service.roles) for service in offered.values()),  # 8 built in
        "grants": len(offered),  # the demo's clients may use each
        "users": 5,
    }


def test_seeded_rows_pass_model_validation() -> None:
    demo_seed(password="pw")
    for vehicle in Vehicle.objects.all():
        assert attributes_clean(vehicle.attributes) == vehicle.attributes
        vehicle.full_clean()
    for model in (Station, VehicleType, Service, ServiceRole):
        for row in model.objects.all():
            row.full_clean()
    assert set(Vehicle.objects.values_list("status", flat=True)) == {Vehicle.Status.OFFLINE}


@pytest.mark.parametrize("type_name", list(VEHICLE_TYPES))
def test_command_vocabularies_follow_the_protocol(type_name: str) -> None:
    commands = VEHICLE_TYPES[type_name]["commands"]
    commands_validate(commands)  # raises on a declaration the client would refuse
    assert all(c.get("group") for c in commands)


def test_manual_services_allow_only_their_vehicles_commands() -> None:
    services = demo_services()
    for slug, type_name in (
        ("drive-car", "Raspberry Pi car"),
        ("fly-drone", "MAVLink quadcopter"),
        ("fly-vtol", "Spektrum VTOL plane"),
    ):
        declared = {c["name"] for c in VEHICLE_TYPES[type_name]["commands"]}
        assert set(services[slug].fields["allowed_commands"]) == declared
    assert "release_payload" not in services["fly-drone"].fields["allowed_commands"]
    # The boat is steered, but its release hook is the rescue's and the parcels'.
    boat = {c["name"] for c in VEHICLE_TYPES["MAVLink boat"]["commands"]}
    assert set(services["drive-boat"].fields["allowed_commands"]) == boat - {"release_payload"}
    assert {"forward", "left", "return_to_home", "release_payload"} <= boat
    assert "take_off" not in boat


def test_every_demo_service_names_the_kind_that_offers_it() -> None:
    kinds = {slug: spec.fields["kind"] for slug, spec in demo_services().items()}
    assert kinds["drive-boat"] == "manual_control"
    assert kinds["parcel-delivery"] == "parcel_delivery"
    demo_seed(password="pw")
    for slug, kind in kinds.items():
        assert Service.objects.get(slug=slug).kind == kind


def test_client_sees_exactly_the_demo_services_and_monitor_none() -> None:
    demo_seed(password="pw")
    User = get_user_model()
    client = User.objects.get(username="client")
    assert set(services_for_user(client).values_list("slug", flat=True)) == DEMO_SLUGS
    assert not services_for_user(User.objects.get(username="monitor")).exists()


def test_one_user_per_role_and_a_second_client_to_spectate() -> None:
    seed = demo_seed(password="pw")
    User = get_user_model()
    for username in ("client", "monitor", "operator", "admin"):
        assert user_roles(User.objects.get(username=username)) == {username}
        assert seed.roles[username] == (username,)
    assert user_roles(User.objects.get(username="client2")) == {"client"}
    assert User.objects.get(username="admin").is_superuser
    assert not User.objects.get(username="client").is_staff
    assert User.objects.get(username="operator").is_staff


def test_random_passwords_are_fresh_on_every_run() -> None:
    first = demo_seed().passwords
    second = demo_seed().passwords
    assert set(first) == {"client", "client2", "monitor", "operator", "admin"}
    assert len(set(second.values())) == 5
    for username, secret in second.items():
        assert first[username] != secret
        assert authenticate(username=username, password=secret) is not None
        assert authenticate(username=username, password=first[username]) is None


def test_password_option_sets_every_user() -> None:
    out = StringIO()
    call_command("seed_demo", password="same-demo-pw", stdout=out, stderr=StringIO())
    for username in ("client", "client2", "monitor", "operator", "admin"):
        assert authenticate(username=username, password="same-demo-pw") is not None
    text = out.getvalue()
    assert "http://127.0.0.1:8000/accounts/login/" in text
    assert "/admin/" in text
    assert "operator" in text and "same-demo-pw" in text


def test_the_logins_name_the_port_the_platform_is_on() -> None:
    # PORT=8100 bin/demo: the agents and the people are sent to the same port.
    out = StringIO()
    call_command("seed_demo", password="pw", platform_url="ws://127.0.0.1:8100", stdout=out)
    assert "Log in at http://127.0.0.1:8100/accounts/login/" in out.getvalue()
    assert ":8000" not in out.getvalue()


def test_the_logins_can_go_to_a_private_file_instead_of_the_terminal(tmp_path: Path) -> None:
    # bin/demo shows them last, once its servers are up, instead of in the seed's output.
    logins = tmp_path / "logins.txt"
    out = StringIO()
    call_command("seed_demo", password="file-pw-123", logins_file=logins, stdout=out)
    assert "file-pw-123" not in out.getvalue()
    assert stat.S_IMODE(logins.stat().st_mode) == 0o600
    text = logins.read_text()
    assert "client2" in text and "file-pw-123" in text
    assert "http://127.0.0.1:8000/accounts/login/" in text


def test_credentials_dir_writes_working_private_configs(tmp_path: Path) -> None:
    target = tmp_path / "agents"
    call_command(
        "seed_demo",
        password="pw",
        credentials_dir=target,
        platform_url="wss://iouv.example",
        stdout=StringIO(),
        stderr=StringIO(),
    )
    paths = sorted(target.glob("*.json"))
    assert {p.stem for p in paths} == set(VEHICLES)
    for path in paths:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        config = json.loads(path.read_text())
        agent = AgentConfig.from_mapping(config)  # what `python -m agents run` reads
        assert agent.platform_public_key == platform_public_key_pem()
        assert agent.uplink_url == "wss://iouv.example/ws/agent/"
        vehicle = vehicle_authenticate(
            vehicle_id=config["vehicle_id"], credential=config["credential"]
        )
        assert vehicle is not None and vehicle.name == config["vehicle_name"] == path.stem
        assert config["adapter"] == vehicle.vehicle_type.adapter
    # The boat is a MAVLink boat, moored on the water.
    boat = json.loads((target / "boat-1.json").read_text())["adapter_options"]
    assert boat["vehicle_class"] == "boat" and is_water(*boat["origin"])
    assert "max_takeoff_m" not in boat
    # A run without the option leaves the credentials alone.
    demo_seed(password="pw")
    config = json.loads((target / "car-1.json").read_text())
    assert vehicle_authenticate(vehicle_id=config["vehicle_id"], credential=config["credential"])


def test_bad_platform_url_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    with pytest.raises(CommandError, match="ws://"):
        call_command(
            "seed_demo",
            credentials_dir=tmp_path / "out",
            platform_url="http://127.0.0.1:8000",
            stdout=StringIO(),
        )
    assert not (tmp_path / "out").exists()
    assert not Vehicle.objects.exists()


def test_reseed_keeps_live_state() -> None:
    demo_seed(password="pw")
    Vehicle.objects.filter(name="car-1").update(status=Vehicle.Status.IDLE, battery=77)
    demo_seed(password="pw")
    car = Vehicle.objects.get(name="car-1")
    assert car.status == Vehicle.Status.IDLE and car.battery == 77
