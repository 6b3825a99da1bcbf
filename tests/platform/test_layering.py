"""The core never names a service kind: not in code, templates, scripts or comments.

A kind is a folder under ``kinds/``; the core (``accounts``, ``fleet``, ``services``,
``iouv``, the root ``templates/`` and ``static/``) reaches kinds through the registry
(``services.kinds``) only. import-linter (``lint-imports``) checks the imports; this
checks the text, which imports cannot show: a slug in a template, a URL in a script, a
default in a model field, a setting. A new folder under ``kinds/`` is covered at once.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CORE = ("accounts", "fleet", "services", "operations", "iouv", "templates", "static")
#: Files left out besides migrations (historical): none; each kind seeds its own demo
#: services (ServiceKind.demo_services).
EXCLUDED: set[Path] = set()


def kind_names() -> list[str]:
    """The installed kinds' folder names."""
    return sorted(
        path.name for path in (ROOT / "kinds").iterdir() if (path / "__init__.py").is_file()
    )


def name_forms(name: str) -> set[str]:
    """How a kind called ``name`` (a folder name) is spelt: ``rescue_at_sea``,
    ``rescue-at-sea``, ``rescue at sea``, ``RescueAtSea``."""
    words = name.split("_")
    return {"_".join(words), "-".join(words), " ".join(words), "".join(w.title() for w in words)}


def kind_pattern(names: list[str]) -> re.Pattern[str]:
    """Any spelling of any of ``names``, as a whole word (``spectator`` is not
    ``spectate``), in any case."""
    forms = sorted({form for name in names for form in name_forms(name)}, key=len, reverse=True)
    return re.compile(
        r"(?<![A-Za-z0-9])(" + "|".join(map(re.escape, forms)) + r")(?![A-Za-z0-9])", re.I
    )


def core_files() -> list[Path]:
    """The core's text files, migrations and EXCLUDED left out."""
    files = []
    for top in CORE:
        for path in sorted((ROOT / top).rglob("*")):
            parts = path.relative_to(ROOT).parts
            if not path.is_file() or "migrations" in parts or "__pycache__" in parts:
                continue
            if path in EXCLUDED:
                continue
            files.append(path)
    return files


def kind_mentions() -> set[tuple[str, str]]:
    """(path, line) for every core line naming a kind."""
    pattern = kind_pattern(kind_names())
    found = set()
    for path in core_files():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # images, fonts
        for line in text.splitlines():
            if pattern.search(line):
                found.add((path.relative_to(ROOT).as_posix(), line.strip()))
    return found


def test_the_kinds_are_found() -> None:
    names = kind_names()
    assert {"manual_control", "spectate"} <= set(names)
    assert kind_pattern(names).search("see kinds/rescue_at_sea/")
    assert kind_pattern(names).search('fetch("/rescue-at-sea/")')
    assert not kind_pattern(names).search("a spectator joins")


def test_the_core_names_no_kind() -> None:
    found = sorted(kind_mentions())
    assert not found, "the core names a kind (use the registry, services.kinds):\n" + "\n".join(
        f"  {path}: {line}" for path, line in found
    )
