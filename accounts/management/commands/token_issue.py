"""``manage.py token_issue USERNAME --name NAME``: an API token, printed once."""

from __future__ import annotations

from typing import Any

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.tokens import token_issue


class Command(BaseCommand):
    help = (
        "Issue a JSON API token for USERNAME and print it once. Only its digest is "
        "stored: copy it now. The token acts as the user, with the user's roles."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("username")
        parser.add_argument("--name", required=True, help="What the token is for.")

    def handle(self, *args: Any, **options: Any) -> None:
        User = get_user_model()
        try:
            user = User.objects.get(**{User.USERNAME_FIELD: options["username"]})
        except User.DoesNotExist:
            raise CommandError(f"no user {options['username']!r}") from None
        if not user.is_active:
            raise CommandError(f"user {options['username']!r} is inactive")
        try:
            token = token_issue(user=user, name=options["name"])
        except ValueError as exc:
            raise CommandError(str(exc)) from None
        # The token alone on stdout, so scripts can capture it; the advice on stderr.
        self.stdout.write(token)
        self.stderr.write("Shown once: store it now (e.g. in your secret manager).")
