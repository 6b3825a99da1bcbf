"""A platform process's garbage collector (operations.collector): what exists at start-up is
frozen out of full collections, and the youngest generation is collected rarely enough
that a request's objects die young."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]


def _collector_of_a_platform_process(tmp_path: Path, **env: str) -> dict[str, Any]:
    """The collector's state once the platform's ASGI application is imported, as a
    server imports it, in a fresh interpreter (embedded defaults)."""
    probe = (
        "import gc, json, iouv.asgi; "
        "print(json.dumps({'thresholds': gc.get_threshold(), 'frozen': gc.get_freeze_count(),"
        " 'tracked': len(gc.get_objects())}))"
    )
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("IOUV_", "DATABASE_URL"))}
    done = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=ROOT,
        env={**clean, "IOUV_DEV_SECRETS": "1", "IOUV_VAR_DIR": str(tmp_path), **env},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def test_start_up_objects_are_frozen_and_young_objects_collected_rarely(tmp_path):
    state = _collector_of_a_platform_process(tmp_path)
    assert state["thresholds"][0] == 10_000
    # The platform's modules, classes and schemas: out of the collector's sight, so a
    # full collection walks only what came after.
    assert state["frozen"] > 50_000
    assert state["tracked"] < state["frozen"] / 10


def test_the_young_threshold_is_a_setting_and_zero_keeps_pythons(tmp_path):
    assert (
        _collector_of_a_platform_process(tmp_path, IOUV_GC_YOUNG_THRESHOLD="2000")["thresholds"][0]
        == 2000
    )
    assert (
        _collector_of_a_platform_process(tmp_path, IOUV_GC_YOUNG_THRESHOLD="0")["thresholds"][0]
        == 700
    )
