"""The agent's configuration file (JSON).

Example::

    {
      "platform_url": "wss://iouv.example.org",
      "vehicle_id": "5f0c...",
      "credential": "...",                      # issued once in the platform's admin
      "platform_public_key_file": "platform.pub.pem",
      "adapter": "car",
      "adapter_options": {"distance_sensor": true},
      "control": {"host": "0.0.0.0", "port": 8765, "public_url": "wss://car-1.example.org"},
      "video": {"source": "v4l2", "device": "/dev/video0"}
    }

A search drone adds its thermal camera, ``"thermal": {"source": "v4l2", "device":
"/dev/video1"}`` (see :func:`agents.thermal.thermal_source_create` and
docs/rescue-agent.md), and ``"video": {"source": "thermal"}`` shows it to users.

Relative paths are taken from the config file's folder.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ConfigError(Exception):
    """The config file is missing, unreadable or wrong; the message names the field."""


@dataclass(frozen=True)
class ControlConfig:
    """Where the agent's control WebSocket listens and how users reach it."""

    host: str = "127.0.0.1"
    port: int = 0  # 0: any free port (simulated fleets)
    public_url: str | None = None  # what the platform gives users; default ws://host:port/


@dataclass(frozen=True)
class AgentConfig:
    """Everything one agent needs to run its vehicle."""

    platform_url: str
    vehicle_id: str
    credential: str
    platform_public_key: str  # PEM
    adapter: str
    adapter_options: Mapping[str, Any] = field(default_factory=dict)
    control: ControlConfig = field(default_factory=ControlConfig)
    video: Mapping[str, Any] | None = None
    thermal: Mapping[str, Any] | None = None
    name: str = ""
    reconnect_min_s: float = 0.5
    reconnect_max_s: float = 30.0

    @property
    def uplink_url(self) -> str:
        return self.platform_url.rstrip("/") + "/ws/agent/"

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
        if not isinstance(key, str) or "PUBLIC KEY" not in key:
            raise ConfigError("platform_public_key: a PEM public key (or _file) is required")
        options = data.get("adapter_options", {})
        if not isinstance(options, Mapping):
            raise ConfigError("adapter_options: must be an object")
        control = data.get("control", {})
        if not isinstance(control, Mapping):
            raise ConfigError("control: must be an object")
        port = control.get("port", 0)
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError("control.port: must be a port number")
        video = data.get("video")
        if video is not None and not isinstance(video, Mapping):
            raise ConfigError("video: must be an object or null")
        thermal = data.get("thermal")
        if thermal is not None:
            if not isinstance(thermal, Mapping):
                raise ConfigError("thermal: must be an object or null")
            # Imported here: the numpy detector is only needed with a thermal camera.
            from agents.thermal import thermal_config_check

            try:
                thermal_config_check(thermal)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
        if video is not None and video.get("source") == "thermal" and thermal is None:
            raise ConfigError("video: the thermal source needs a thermal section")
        return cls(
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
            ),
            video=dict(video) if video is not None else None,
            thermal=dict(thermal) if thermal is not None else None,
            name=str(data.get("vehicle_name") or data.get("name") or ""),
        )

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
