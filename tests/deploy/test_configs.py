"""The files production runs (deploy/) are valid as shipped: systemd accepts the units,
nginx the site, and the site routes, limits and answers as docs/operations.md says."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from benchmarks.nginx_proxy import NginxUnavailable
from tests.janus import janus_ensure
from tests.production import (
    DEPLOY,
    nginx_command,
    nginx_prepared,
    nginx_site,
    units_rendered,
)
from tests.tls import certificates_make


def test_systemd_accepts_every_unit(tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("needs systemd-analyze (Debian's systemd package)")
    janus_ensure()  # verify checks that every unit's command exists
    units = units_rendered(tmp_path)
    assert {u.name for u in units} >= {
        "iouv-web@8001.service",
        "iouv-ws@8101.service",
        "iouv-worker.service",
        "iouv-beat.service",
        "iouv-janus.service",
        "iouv.target",
    }
    done = subprocess.run(
        [analyze, "verify", *map(str, units)], capture_output=True, text=True, check=False
    )
    # verify fails on unknown keys, bad values and commands that do not exist.
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Unknown" not in done.stderr and "not executable" not in done.stderr, done.stderr


def test_every_unit_stops_with_sigterm_and_time_to_finish() -> None:
    """Deploys stop processes with SIGTERM: each unit says so and leaves the process
    time to finish what it does (requests, tasks, closing sockets)."""
    for unit in (DEPLOY / "systemd").glob("*.service"):
        text = unit.read_text()
        assert "KillSignal=SIGTERM" in text, unit.name
        assert "TimeoutStopSec=" in text, unit.name
        assert "EnvironmentFile=/etc/iouv/iouv.env" in text, unit.name


def test_nginx_accepts_the_site(tmp_path: Path) -> None:
    try:
        certificates = certificates_make(tmp_path / "tls")
        site = nginx_site(
            web=[18001, 18002],
            ws=[18101, 18102],
            https=18443,
            http=18080,
            certificates=certificates,
            static_root=tmp_path / "static",
        )
        nginx_prepared(tmp_path / "nginx", site)
        done = subprocess.run(
            nginx_command(tmp_path / "nginx", "-t"), capture_output=True, text=True, check=False
        )
    except NginxUnavailable as exc:
        pytest.skip(str(exc))
    assert done.returncode == 0, done.stderr
    assert "syntax is ok" in done.stderr and "test is successful" in done.stderr
