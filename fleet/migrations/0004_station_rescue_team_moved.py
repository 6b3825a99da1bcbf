"""A station's rescue team moved to the rescue kind (rescue_at_sea.RescueTeam), which
copies it over before these fields go."""

from django.db import migrations


class Migration(migrations.Migration):
    dependencies = [
        ("fleet", "0003_agent_messages"),
    ]

    operations = [
        migrations.RemoveField(model_name="station", name="rescue_team_email"),
        migrations.RemoveField(model_name="station", name="rescue_team_name"),
        migrations.RemoveField(model_name="station", name="rescue_team_phone"),
        migrations.RemoveField(model_name="station", name="rescue_team_webhook"),
    ]
