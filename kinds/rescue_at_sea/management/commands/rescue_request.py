"""Start a person-rescue mission from the command line (the demo uses it).

    python manage.py rescue_request --user client --demo
    python manage.py rescue_request --user client --around 40.6440,-8.7560 --size 300x200
    python manage.py rescue_request --user client --altitude 35 \
        --area '[[40.64,-8.76],[40.64,-8.75],[40.645,-8.75]]'
"""

from __future__ import annotations

import json
from typing import Any

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError, CommandParser

from agents.geo import offset
from kinds.rescue_at_sea.kind import RescueAtSea
from kinds.rescue_at_sea.request import rescue_request
from services.kit import CASTAWAY, AssignmentError, RequestError
from services.models import Service


def _pair(text: str, sep: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(part) for part in text.split(sep))
    except ValueError:
        raise CommandError(f"{what}: expected two numbers separated by {sep!r}") from None
    return a, b


class Command(BaseCommand):
    help = "Request a person rescue at sea over an area, as a given user."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--user", required=True, help="who asks (must hold the grant)")
        where = parser.add_mutually_exclusive_group(required=True)
        where.add_argument("--area", help="the polygon as JSON [[lat, lon], ...]")
        where.add_argument("--around", help="LAT,LON: a rectangle centred here")
        where.add_argument(
            "--demo",
            action="store_true",
            help="an area around the demo's simulated castaway (not centred on them)",
        )
        parser.add_argument("--size", default="300x200", help="WIDTHxHEIGHT in metres")
        parser.add_argument("--altitude", type=float, default=None, help="search altitude (m)")
        parser.add_argument("--service", default="", help="service slug (default: the rescue)")

    def handle(self, *args: Any, **options: Any) -> None:
        user = get_user_model().objects.filter(username=options["user"]).first()
        if user is None:
            raise CommandError(f"no user {options['user']!r}")
        services = Service.objects.filter(kind=RescueAtSea.name, is_active=True)
        if options["service"]:
            services = services.filter(slug=options["service"])
        service = services.first()
        if service is None:
            raise CommandError("no active rescue service (run seed_demo)")
        if options["area"]:
            try:
                area = json.loads(options["area"])
            except ValueError:
                raise CommandError("--area is not valid JSON") from None
        else:
            if options["demo"]:
                lat, lon = offset(CASTAWAY, 40.0, -60.0)
            else:
                lat, lon = _pair(options["around"], ",", "--around")
            width, height = _pair(options["size"], "x", "--size")
            corner = offset((lat, lon), -height / 2, -width / 2)
            area = [
                list(corner),
                list(offset(corner, 0, width)),
                list(offset(corner, height, width)),
                list(offset(corner, height, 0)),
            ]
        try:
            session = rescue_request(
                user=user, service=service, area=area, altitude_m=options["altitude"]
            )
        except (RequestError, AssignmentError) as exc:
            raise CommandError(str(exc)) from None
        self.stdout.write(f"rescue {session.pk} requested; watch it at /sessions/{session.pk}/")
