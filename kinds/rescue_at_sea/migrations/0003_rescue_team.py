"""Each station's rescue team becomes the rescue kind's own row (RescueTeam), copied
from the station's fields before the fleet drops them."""

import django.db.models.deletion
from django.db import migrations, models


def copy_teams(apps, schema_editor):  # type: ignore[no-untyped-def]
    Station = apps.get_model("fleet", "Station")
    RescueTeam = apps.get_model("rescue_at_sea", "RescueTeam")
    for station in Station.objects.all():
        fields = {
            "name": station.rescue_team_name,
            "email": station.rescue_team_email,
            "phone": station.rescue_team_phone,
            "webhook": station.rescue_team_webhook,
        }
        if any(fields.values()):
            RescueTeam.objects.update_or_create(station=station, defaults=fields)


class Migration(migrations.Migration):
    dependencies = [
        ("fleet", "0003_agent_messages"),
        ("rescue_at_sea", "0002_notices_moved_to_core"),
    ]
    # The copy reads the station's fields: it must run before they are removed.
    run_before = [("fleet", "0004_station_rescue_team_moved")]

    operations = [
        migrations.CreateModel(
            name="RescueTeam",
            fields=[
                (
                    "station",
                    models.OneToOneField(
                        on_delete=django.db.models.deletion.CASCADE,
                        primary_key=True,
                        related_name="rescue_team",
                        serialize=False,
                        to="fleet.station",
                    ),
                ),
                ("name", models.CharField(blank=True, max_length=100)),
                ("email", models.EmailField(blank=True, max_length=254)),
                ("phone", models.CharField(blank=True, max_length=40)),
                ("webhook", models.URLField(blank=True)),
            ],
        ),
        migrations.RunPython(copy_teams, migrations.RunPython.noop),
    ]
