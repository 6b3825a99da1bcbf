"""The missions as plug-ins: the registry finds each folder, the vehicle task's
``mission`` is the tagged union of their specs, a spec is checked wherever it is made
(decoded by the agent, built by the platform), it travels as the JSON object the
platform always signed, and the published schemas (docs/protocol/schema/mission.schema
.json, and each mission's spec.schema.json in its folder) say what the decoder
accepts."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from agents.missions.delivery.spec import DeliverySpec
from agents.missions.kit import MissionRunner
from agents.missions.parcel.spec import ParcelSpec
from agents.missions.registry import (
    MISSIONS_DIR,
    UnknownMission,
    mission,
    mission_decode,
    mission_names,
    missions,
    sensors,
)
from agents.missions.return_home.spec import ReturnSpec
from agents.missions.search.spec import SearchSpec
from agents.missions.spec import MissionError
from agents.protocol import ProtocolError, VehicleTask, generate_keypair, load_private_key
from agents.protocol.schema import mission_spec_path, schema_path
from tests.agents.documents import task_for
from tests.agents.mission_rig import HOME, MALFORMED, delivery, search

ROOT = Path(__file__).resolve().parents[3]
SCHEMA = jsonschema.Draft202012Validator(
    json.loads(schema_path("mission").read_text(encoding="utf-8"))
)
#: Each mission's published spec schema, by kind.
SPECS = {
    kind: jsonschema.Draft202012Validator(json.loads(path.read_text(encoding="utf-8")))
    for kind, path in ((k, mission_spec_path(m.name)) for k, m in missions().items())
}


def schema_valid(data: Any) -> bool:
    """What a client reading the published files accepts: the mission document, then
    the spec of the mission its ``kind`` names."""
    if not SCHEMA.is_valid(data):
        return False
    spec = SPECS.get(data["kind"])
    return spec is not None and spec.is_valid(data)


def test_the_registry_finds_every_mission_folder() -> None:
    folders = sorted(p.parent.name for p in MISSIONS_DIR.glob("[!_]*/__init__.py"))
    assert mission_names() == folders
    assert {"delivery", "parcel", "return_home", "search"} <= set(folders)
    by_kind = missions()
    assert {kind: by_kind[kind].spec for kind in ("delivery", "parcel", "return", "search")} == {
        "delivery": DeliverySpec,
        "parcel": ParcelSpec,
        "return": ReturnSpec,
        "search": SearchSpec,
    }
    assert sorted(m.name for m in by_kind.values()) == folders
    for declared in by_kind.values():
        assert issubclass(declared.runner(), MissionRunner)
    # The search's thermal camera can be shown as video.
    assert sensors()["thermal"].video is not None
    with pytest.raises(UnknownMission, match="installed: delivery, parcel, return_home"):
        mission("rescue")


def test_the_platform_loads_no_runner_and_no_camera_library() -> None:
    """The specs come with agents.protocol (the platform's only agent code): neither a
    runner, the flight kit, numpy nor PyAV is imported with them."""
    code = (
        "import sys, agents.protocol as p; p.VehicleTask; "
        "print(sorted(m for m in sys.modules if m.startswith(('numpy', 'av', 'aiortc')) "
        "or m.endswith(('.runner', '.kit', '.thermal', '.video'))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(("data", "reason"), MALFORMED)
def test_a_malformed_mission_is_refused_naming_the_field(data: Any, reason: str) -> None:
    with pytest.raises(MissionError) as exc:
        mission_decode(data)
    # The decoder says "mission.x: problem" where a refused task says "'mission.x': ...".
    assert reason.replace("'", "") in str(exc.value)


@pytest.mark.parametrize(("data", "reason"), MALFORMED)
def test_a_task_with_a_malformed_mission_is_refused(data: Any, reason: str) -> None:
    claims = task_for("v-1", ()).to_payload()
    with pytest.raises(ProtocolError) as exc:
        VehicleTask.from_payload({**claims, "mission": data})
    assert exc.value.code == "bad_field" and reason in str(exc.value)
    assert exc.value.field is not None and exc.value.field.startswith("mission")


def test_a_spec_built_in_code_is_checked_as_decoding_checks_it() -> None:
    with pytest.raises(MissionError, match=r"mission\.altitude_m: Expected `float` >= 1"):
        SearchSpec(id="s", altitude_m=-5, waypoints=(HOME,))
    with pytest.raises(MissionError, match=r"mission\.start_index: an integer in \[0, 0\]"):
        SearchSpec(id="s", altitude_m=40, waypoints=(HOME,), start_index=1)
    with pytest.raises(MissionError, match=r"mission\.waypoints\[0\]\[0\]"):
        SearchSpec(id="s", altitude_m=40, waypoints=((95.0, 0.0),))
    with pytest.raises(MissionError, match=r"mission\.drop_altitude_m"):
        DeliverySpec(id="d", target=HOME, altitude_m=10, drop_altitude_m=20)
    # Normalised as decoding normalises: numbers are floats, points tuples.
    spec = DeliverySpec(id="d", target=[HOME[0], HOME[1]], altitude_m=30)  # type: ignore[arg-type]
    assert spec == mission_decode(delivery("d", target=list(HOME), altitude_m=30))
    assert spec.target == HOME and isinstance(spec.altitude_m, float)


def test_a_task_carries_its_mission_as_the_json_the_platform_always_signed() -> None:
    private = load_private_key(generate_keypair()[0])
    spec = mission_decode(search())
    task = task_for("v-1", (), mission=spec)
    claims = task.to_payload()
    assert claims["mission"] == search()  # the same object, "kind" and all
    assert list(claims["mission"])[:2] == ["kind", "id"]
    token = task.sign(private)
    assert token.count(".") == 2
    again = VehicleTask.from_payload(claims)
    assert again.mission == spec and isinstance(again.mission, SearchSpec)
    # A task is made of checked parts: a plain object is not a mission.
    with pytest.raises(ProtocolError, match="mission"):
        VehicleTask(**{**_fields(task), "mission": search()})


def _fields(task: VehicleTask) -> dict[str, Any]:
    return {name: getattr(task, name) for name in task.__struct_fields__}


def test_each_kind_is_flown_by_its_own_folders_runner() -> None:
    for kind, declared in missions().items():
        assert declared.spec.mission_kind() == kind
        assert declared.runner().__module__ == f"agents.missions.{declared.name}.runner"


# --- the published schema ------------------------------------------------------------------


def test_every_mission_publishes_its_spec_in_its_own_folder() -> None:
    jsonschema.Draft202012Validator.check_schema(SCHEMA.schema)
    # The mission document names no mission: a new one changes nothing outside its folder.
    text = schema_path("mission").read_text(encoding="utf-8")
    assert not any(f'"{kind}"' in text for kind in missions())
    assert set(SPECS) == set(missions())
    for kind, declared in missions().items():
        assert mission_spec_path(declared.name) == MISSIONS_DIR / declared.name / "spec.schema.json"
        jsonschema.Draft202012Validator.check_schema(SPECS[kind].schema)
        assert SPECS[kind].is_valid({"kind": kind}) is False  # its own fields are required


VALID = [
    search(),
    delivery(),
    {"kind": "return", "id": "h"},
    {
        "kind": "parcel",
        "id": "p",
        "pickup": list(HOME),
        "dropoff": list(HOME),
        "altitude_m": 15,
    },
]
#: Rules across fields JSON Schema does not express: the specs alone refuse these.
CROSS_FIELD = [search(start_index=6), delivery(drop_altitude_m=40)]


@pytest.mark.parametrize("data", VALID)
def test_what_the_decoder_accepts_the_schema_accepts(data: dict[str, Any]) -> None:
    spec = mission_decode(data)
    assert schema_valid(data) and schema_valid(spec.to_payload())


@pytest.mark.parametrize(("data", "reason"), MALFORMED)
def test_what_the_decoder_refuses_the_schema_refuses(data: Any, reason: str) -> None:
    with pytest.raises(MissionError):
        mission_decode(data)
    assert schema_valid(data) is (data in CROSS_FIELD)


# --- the contracts -----------------------------------------------------------------------------


def test_the_import_contracts_keep_every_mission_independent() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = {c["id"]: c for c in config["tool"]["importlinter"]["contracts"]}
    independent = contracts["missions-independent"]
    assert independent["type"] == "independence"
    # Every folder, by a wildcard: a new mission is held to it without naming it.
    assert independent["modules"] == ["agents.missions.*"]
    shared = {"kit", "plan", "spec", "registry"}
    ignored = {
        target
        for source, target in (line.split(" -> ") for line in independent["ignore_imports"])
        if source == "agents.**"
    }
    assert ignored == {f"agents.missions.{name}" for name in shared}
    # What a mission's tests import is theirs (they set the stage with the agent's parts).
    assert "agents.missions.*.tests.** -> agents.**" in independent["ignore_imports"]
    assert not shared & set(mission_names())
