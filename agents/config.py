"""The agent's configuration file (JSON).

Example::

    {
      "platform_url": "wss://iouv.example.org",
      "vehicle_id": "5f0c...",
      "credential": "...",                      # issued once in the platform's admin
      "platform_public_key_file": "platform.pub.pem",
      "platform_jwks_url": "https://iouv.example.org/.well-known/jwks.json",
      "adapter": "car",
      "adapter_options": {"distance_sensor": true},
      "control": {"host": "0.0.0.0", "port": 8765, "public_url": "wss://car-1.example.org",
                  "max_grant_lifetime_s": 900},
      "video": {"source": "v4l2", "device": "/dev/video0"},
      "webrtc": {"ice_servers": ["stun:stun.example.org:3478"]}
    }

A mission's sensor has a section of its own, named by the mission
(:class:`agents.missions.registry.Sensor`): a search drone adds its thermal camera,
``"thermal": {"source": "v4l2", "device": "/dev/video1"}`` (see
:func:`agents.missions.search.thermal.thermal_source_create` and docs/rescue-agent.md),
and ``"video": {"source": "thermal"}`` shows it to users.

The camera missions photograph with (pictures straight down, to map an area) is the
``photo`` section, ``{"source": "nadir" | "v4l2", "hfov_deg": ..., "width": ...,
"height": ...}`` (see :mod:`agents.stills`).

The platform's public keys come from any of ``platform_public_key`` (PEM text),
``platform_public_key_file`` (a PEM file), ``platform_jwks_file`` (a JWKS file) and
``platform_jwks_url`` (a JWKS fetched once when the config is loaded: https, or http on
loopback only); the agent trusts all the keys given. Once connected it adopts the key set
the platform's ``welcome`` carries (a key rotation), unless
``"platform_jwks_from_welcome": false`` pins the configured keys.

``webrtc`` configures the agent's WebRTC connections (:mod:`agents.rtc`):
``ice_servers`` (STUN/TURN used beside the ones the platform sends with each offer),
``ice_host_addresses`` (restrict the local addresses offered; ``["127.0.0.1"]`` on a
loopback-only machine), ``max_peers``, or ``"enabled": false`` to answer no WebRTC
offer at all. Absent, the agent accepts offers with the platform's servers alone.

``uplink_ping_interval_s`` (2) and ``uplink_ping_timeout_s`` (3) set the uplink's
keepalive: an uplink whose pong is that late is given up, and the agent reconnects
(through nginx, to a platform machine that is there); see agents.uplink.

``records`` says where the flight record waits for the platform (:mod:`agents.recording`,
docs/records.md): ``{"dir": "records", "max_bytes": 268435456}``; by default
``$IOUV_VAR_DIR/agent/<vehicle id>/records`` (``var/`` without the variable), 256 MiB.
The files missions make (photos, :mod:`agents.artifacts`) wait beside it, in
``artifacts``, under the same bound.

Relative paths are taken from the config file's folder.
"""

from __future__ import annotations

import ipaddress
import json
import os
import urllib.error
import urllib.request
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final
from urllib.parse import urlsplit

from agents.missions.registry import sensors as mission_sensors
from agents.protocol import KeySet, ProtocolError
from agents.uplink import PING_INTERVAL_S, PING_TIMEOUT_S

#: Bounds on fetching ``platform_jwks_url``: a JWKS is a few hundred bytes.
JWKS_FETCH_TIMEOUT_S: Final = 10.0
JWKS_MAX_BYTES: Final = 64 * 1024
#: What the ``webrtc`` section may hold.
#: How much of the flight record may wait on the vehicle for the platform by default.
RECORD_MAX_BYTES: Final = 256 * 1024 * 1024
WEBRTC_OPTIONS: Final = frozenset({"enabled", "ice_servers", "ice_host_addresses", "max_peers"})


class ConfigError(Exception):
    """The config file is missing, unreadable or wrong; the message names the field."""


#: The longest user grant the agent accepts by default: three times the platform's
#: default grant lifetime (IOUV_GRANT_TTL_S, 300 s). A platform set to give longer grants
#: needs its agents' ``control.max_grant_lifetime_s`` raised to match.
MAX_GRANT_LIFETIME_S: Final = 900.0


@dataclass(frozen=True)
class ControlConfig:
    """Where the agent's control WebSocket listens and how users reach it, and the
    longest grant it accepts (``exp - iat``, seconds): a grant valid longer is refused
    with ``lifetime_too_long``."""

    host: str = "127.0.0.1"
    port: int = 0  # 0: any free port (simulated fleets)
    public_url: str | None = None  # what the platform gives users; default ws://host:port/
    max_grant_lifetime_s: float = MAX_GRANT_LIFETIME_S


@dataclass(frozen=True)
class RecordsConfig:
    """Where the flight record waits on the vehicle until the platform has it
    (agents.recording), and how much of it may wait. ``directory`` None: the agent's
    var directory (``$IOUV_VAR_DIR``, else ``var/``), ``agent/<vehicle id>/records``."""

    directory: Path | None = None
    max_bytes: int = RECORD_MAX_BYTES

    def path_for(self, vehicle_id: str) -> Path:
        """The directory of ``vehicle_id``'s record."""
        if self.directory is not None:
            return self.directory
        return Path(os.environ.get("IOUV_VAR_DIR") or "var") / "agent" / vehicle_id / "records"

    def artifacts_path_for(self, vehicle_id: str) -> Path:
        """Where the files missions make wait (agents.artifacts): ``artifacts`` beside
        the record's directory, bounded by the same ``max_bytes``."""
        return self.path_for(vehicle_id).parent / "artifacts"


@dataclass(frozen=True)
class AgentConfig:
    """Everything one agent needs to run its vehicle."""

    platform_url: str
    vehicle_id: str
    credential: str
    #: PEM text (one or more keys); may be empty when ``platform_jwks`` is given.
    platform_public_key: str
    adapter: str
    adapter_options: Mapping[str, Any] = field(default_factory=dict)
    control: ControlConfig = field(default_factory=ControlConfig)
    video: Mapping[str, Any] | None = None
    #: The sections of the missions' sensors this vehicle has, by name (``thermal``).
    sensors: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    #: The camera missions photograph with (agents.stills), or None.
    photo: Mapping[str, Any] | None = None
    webrtc: Mapping[str, Any] = field(default_factory=dict)
    name: str = ""
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0
    #: The uplink's keepalive (agents.uplink): a ping this often, the uplink given up
    #: when its pong is this late. Together (plus 1 s to close) they bound how long an
    #: agent stays on a platform machine that dropped off the network.
    uplink_ping_interval_s: float = PING_INTERVAL_S
    uplink_ping_timeout_s: float = PING_TIMEOUT_S
    #: A JWK Set (parsed JSON) of further trusted platform keys, from a file or a URL.
    platform_jwks: Mapping[str, Any] | None = None
    #: Adopt the key set the platform's ``welcome`` carries (how rotations reach agents).
    platform_jwks_from_welcome: bool = True
    records: RecordsConfig = field(default_factory=RecordsConfig)

    @property
    def uplink_url(self) -> str:
        return self.platform_url.rstrip("/") + "/ws/agent/"

    def platform_keys(self) -> KeySet:
        """Every platform key this config trusts (PEM keys, then JWKS keys).

        Raises ConfigError naming the field when a key is unusable or there is none.
        """
        keys = None
        if self.platform_public_key:
            try:
                keys = KeySet.from_pem(self.platform_public_key)
            except ProtocolError as exc:
                raise ConfigError(f"platform_public_key: {exc.message}") from None
        if self.platform_jwks is not None:
            try:
                from_jwks = KeySet.from_jwks(self.platform_jwks)
            except ProtocolError as exc:
                raise ConfigError(f"platform_jwks: {exc.message}") from None
            keys = from_jwks if keys is None else keys.union(from_jwks)
        if keys is None:
            raise ConfigError("platform_public_key: a PEM public key or a JWKS is required")
        return keys

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], *, base_dir: Path | None = None) -> AgentConfig:
        """Build a config from parsed JSON; raises ConfigError naming the bad field."""
        if not isinstance(data, Mapping):
            raise ConfigError("config: must be a JSON object")
        base = base_dir or Path.cwd()

        def text(name: str, *, required: bool = True) -> str:
            value = data.get(name, "")
            if not isinstance(value, str) or (required and not value):
                raise ConfigError(f"{name}: required text")
            return value

        url = text("platform_url")
        if not url.startswith(("ws://", "wss://")):
            raise ConfigError("platform_url: must start with ws:// or wss://")
        key = data.get("platform_public_key")
        key_file = data.get("platform_public_key_file")
        if not key and isinstance(key_file, str) and key_file:
            try:
                key = (base / key_file).read_text()
            except OSError as exc:
                raise ConfigError(f"platform_public_key_file: cannot read: {exc}") from None
        jwks = _jwks_configured(data, base)
        if jwks is None and (not isinstance(key, str) or "PUBLIC KEY" not in key):
            raise ConfigError(
                "platform_public_key: a PEM public key (or _file), or platform_jwks_file or "
                "platform_jwks_url, is required"
            )
        if not isinstance(key, str):
            key = ""
        from_welcome = data.get("platform_jwks_from_welcome", True)
        if not isinstance(from_welcome, bool):
            raise ConfigError("platform_jwks_from_welcome: must be true or false")
        options = data.get("adapter_options", {})
        if not isinstance(options, Mapping):
            raise ConfigError("adapter_options: must be an object")
        control = data.get("control", {})
        if not isinstance(control, Mapping):
            raise ConfigError("control: must be an object")
        port = control.get("port", 0)
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError("control.port: must be a port number")
        max_grant = control.get("max_grant_lifetime_s", MAX_GRANT_LIFETIME_S)
        if isinstance(max_grant, bool) or not isinstance(max_grant, int | float) or max_grant <= 0:
            raise ConfigError("control.max_grant_lifetime_s: must be a positive number of seconds")
        video = data.get("video")
        if video is not None and not isinstance(video, Mapping):
            raise ConfigError("video: must be an object or null")
        sensors = _sensors_configured(data)
        photo = data.get("photo")
        if photo is not None:
            if not isinstance(photo, Mapping):
                raise ConfigError("photo: must be an object or null")
            # Imported only for an agent with a photo camera (it loads numpy).
            from agents.stills import photo_options_check

            try:
                photo_options_check(photo)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        webrtc = data.get("webrtc", {})
        if not isinstance(webrtc, Mapping):
            raise ConfigError("webrtc: must be an object")
        unknown = set(webrtc) - WEBRTC_OPTIONS
        if unknown:
            raise ConfigError(f"webrtc: unknown option(s) {', '.join(sorted(unknown))}")
        if not isinstance(webrtc.get("enabled", True), bool):
            raise ConfigError("webrtc.enabled: must be true or false")
        source = video.get("source") if video is not None else None
        if source in mission_sensors() and source not in sensors:
            raise ConfigError(f"video: the {source} source needs a {source} section")
        records = data.get("records", {})
        if not isinstance(records, Mapping):
            raise ConfigError("records: must be an object")
        record_dir = records.get("dir")
        if record_dir is not None and not (isinstance(record_dir, str) and record_dir):
            raise ConfigError("records.dir: must be a directory path")
        record_max = records.get("max_bytes", RECORD_MAX_BYTES)
        if isinstance(record_max, bool) or not isinstance(record_max, int) or record_max <= 0:
            raise ConfigError("records.max_bytes: must be a positive number of bytes")
        keepalive: dict[str, float] = {}
        for name, default in (
            ("uplink_ping_interval_s", PING_INTERVAL_S),
            ("uplink_ping_timeout_s", PING_TIMEOUT_S),
        ):
            value = data.get(name, default)
            if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
                raise ConfigError(f"{name}: must be a positive number of seconds")
            keepalive[name] = float(value)
        config = cls(
            platform_url=url,
            vehicle_id=text("vehicle_id"),
            credential=text("credential"),
            platform_public_key=key,
            adapter=text("adapter"),
            adapter_options=dict(options),
            control=ControlConfig(
                host=str(control.get("host", "127.0.0.1")),
                port=port,
                public_url=control.get("public_url") or None,
                max_grant_lifetime_s=float(max_grant),
            ),
            video=dict(video) if video is not None else None,
            sensors=sensors,
            photo=dict(photo) if photo is not None else None,
            webrtc=dict(webrtc),
            name=str(data.get("vehicle_name") or data.get("name") or ""),
            platform_jwks=jwks,
            platform_jwks_from_welcome=from_welcome,
            uplink_ping_interval_s=keepalive["uplink_ping_interval_s"],
            uplink_ping_timeout_s=keepalive["uplink_ping_timeout_s"],
            records=RecordsConfig(
                directory=base / record_dir if record_dir else None, max_bytes=record_max
            ),
        )
        config.platform_keys()  # refuse unusable keys now, naming the field
        return config

    @classmethod
    def load(cls, path: str | Path) -> AgentConfig:
        """Read and validate a JSON config file."""
        p = Path(path)
        try:
            data = json.loads(p.read_text())
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read: {exc}") from None
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{p}: not JSON: {exc}") from None
        return cls.from_mapping(data, base_dir=p.parent)


def _sensors_configured(data: Mapping[str, Any]) -> dict[str, Mapping[str, Any]]:
    """The sections of the missions' sensors in ``data``, each checked by its mission
    (nothing is opened). Raises ConfigError naming the bad key."""
    sensors: dict[str, Mapping[str, Any]] = {}
    for section, sensor in mission_sensors().items():
        options = data.get(section)
        if options is None:
            continue
        if not isinstance(options, Mapping):
            raise ConfigError(f"{section}: must be an object or null")
        try:
            sensor.check(options)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        sensors[section] = dict(options)
    return sensors


def _jwks_configured(data: Mapping[str, Any], base: Path) -> dict[str, Any] | None:
    """The JWKS named by ``platform_jwks_file`` or ``platform_jwks_url``, if either is set
    (both together is ambiguous and refused). Raises ConfigError naming the field."""
    jwks_file = data.get("platform_jwks_file")
    jwks_url = data.get("platform_jwks_url")
    if jwks_file is not None and jwks_url is not None:
        raise ConfigError("platform_jwks_file: give it or platform_jwks_url, not both")
    if jwks_file is not None:
        if not isinstance(jwks_file, str) or not jwks_file:
            raise ConfigError("platform_jwks_file: must be a file name")
        try:
            text = (base / jwks_file).read_text()
        except OSError as exc:
            raise ConfigError(f"platform_jwks_file: cannot read: {exc}") from None
        return _jwks_parsed(text, "platform_jwks_file")
    if jwks_url is not None:
        if not isinstance(jwks_url, str) or not jwks_url:
            raise ConfigError("platform_jwks_url: must be a URL")
        return jwks_fetch(jwks_url)
    return None


def _jwks_parsed(text: str, name: str) -> dict[str, Any]:
    try:
        jwks = json.loads(text)
    except ValueError as exc:
        raise ConfigError(f"{name}: not JSON: {exc}") from None
    try:
        KeySet.from_jwks(jwks)
    except ProtocolError as exc:
        raise ConfigError(f"{name}: {exc.message}") from None
    return dict(jwks)


def is_loopback_host(host: str) -> bool:
    """Is ``host`` this machine (``localhost`` or a loopback address)?"""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def jwks_fetch(
    url: str, *, timeout_s: float = JWKS_FETCH_TIMEOUT_S, max_bytes: int = JWKS_MAX_BYTES
) -> dict[str, Any]:
    """Fetch the platform's JWKS from ``url`` (its ``/.well-known/jwks.json``).

    The keys are trusted from then on, so the server must be authenticated: ``https://``
    only, or ``http://`` to a loopback address (a platform on the same machine). Returns
    the JWKS (validated: every key a public Ed25519 key). Raises ConfigError naming
    ``platform_jwks_url`` for another scheme, a network failure or timeout, a non-200
    answer, a body over ``max_bytes``, or a body that is not such a JWKS.
    """
    parts = urlsplit(url)
    local_http = parts.scheme == "http" and is_loopback_host(parts.hostname or "")
    if not (parts.scheme == "https" or local_http):
        raise ConfigError("platform_jwks_url: must be https:// (or http:// on loopback)")
    request = urllib.request.Request(url, headers={"Accept": "application/json"})
    # No proxies: the platform is reached directly, as by the uplink.
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))
    try:
        with opener.open(request, timeout=timeout_s) as response:
            if response.status != 200:
                raise ConfigError(f"platform_jwks_url: answered {response.status}")
            body = response.read(max_bytes + 1)
    except urllib.error.HTTPError as exc:
        raise ConfigError(f"platform_jwks_url: answered {exc.code}") from None
    except (urllib.error.URLError, OSError, TimeoutError) as exc:
        raise ConfigError(f"platform_jwks_url: cannot fetch: {exc}") from None
    if len(body) > max_bytes:
        raise ConfigError(f"platform_jwks_url: answer is over {max_bytes} bytes")
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError("platform_jwks_url: answer is not UTF-8") from None
    return _jwks_parsed(text, "platform_jwks_url")
