"""``manage.py seed_demo``: the demo fleet, services and users (see services.demo)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from django.contrib.auth.password_validation import validate_password
from django.core.exceptions import ValidationError
from django.core.management.base import BaseCommand, CommandError, CommandParser

from services.demo import DEFAULT_PLATFORM_URL, demo_seed, site_url


class Command(BaseCommand):
    help = (
        "Create or update the demo world: two stations near Aveiro, the paper's fleet, "
        "its services and one user per role (two clients). Safe to run again."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument(
            "--password",
            help="Set this password for every demo user (default: a fresh random one each).",
        )
        parser.add_argument(
            "--credentials-dir",
            type=Path,
            help="Issue every demo vehicle a fresh credential and write its agent config "
            "(<name>.json, mode 0600) into this directory. Earlier credentials stop working.",
        )
        parser.add_argument(
            "--platform-url",
            default=DEFAULT_PLATFORM_URL,
            help=f"Platform URL written into the agent configs (default {DEFAULT_PLATFORM_URL}).",
        )
        parser.add_argument(
            "--logins-file",
            type=Path,
            help="Write the users and their passwords into this file (mode 0600) instead "
            "of printing them, for a caller that shows them once its servers are up.",
        )

    def handle(self, *args: Any, **options: Any) -> None:
        password: str | None = options["password"]
        if password is not None:
            try:
                validate_password(password)
            except ValidationError as exc:
                # A demo may want a short password; say so rather than refuse it.
                self.stderr.write(
                    self.style.WARNING(f"Weak password, fine for a demo only: {exc.messages[0]}")
                )
        try:
            seed = demo_seed(
                password=password,
                credentials_dir=options["credentials_dir"],
                platform_url=options["platform_url"],
            )
        except ValueError as exc:
            raise CommandError(str(exc)) from exc

        self.stdout.write(self.style.SUCCESS("Demo world ready."))
        site = site_url(options["platform_url"])
        width = max(len("username"), *(len(name) for name in seed.passwords))
        lines = [f"{'username':<{width}}  {'roles':<10}  password"]
        for username, secret in seed.passwords.items():
            roles = ", ".join(seed.roles.get(username, ()))
            lines.append(f"{username:<{width}}  {roles:<10}  {secret}")
        lines.append(f"\nLog in at {site}/accounts/login/ (clients) or {site}/admin/ (staff).")
        logins: Path | None = options["logins_file"]
        if logins is not None:
            logins.parent.mkdir(parents=True, exist_ok=True)
            logins.touch(mode=0o600)
            logins.chmod(0o600)  # passwords: readable by this user only
            logins.write_text("\n".join(lines) + "\n")
        else:
            self.stdout.write("\n" + "\n".join(lines))
        if seed.config_paths:
            self.stdout.write(f"\nAgent configs ({len(seed.config_paths)}, fresh credentials):")
            for path in seed.config_paths:
                self.stdout.write(f"  {path}")
