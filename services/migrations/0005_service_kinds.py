"""Services name their kind (services.kinds); the rescue's models move to its own app.

``workflow`` becomes ``kind`` (same values), ``mode`` goes (a kind says whether its
user drives). ``Mission`` and ``MissionNotification`` leave this app's state only: their
tables stay as they are and belong to ``rescue_at_sea`` from its first migration on.
"""

import services.models
from django.db import migrations, models


class Migration(migrations.Migration):

    dependencies = [
        ("services", "0004_service_max_sessions_per_user"),
    ]

    operations = [
        migrations.RenameField(model_name="service", old_name="workflow", new_name="kind"),
        migrations.AlterField(
            model_name="service",
            name="kind",
            field=models.CharField(
                default="manual_control",
                help_text="What kind of service this is (services.kinds): what a request "
                "sets going, what the user and the vehicles get.",
                max_length=40,
                validators=[services.models._kind_installed],
            ),
        ),
        migrations.RemoveField(model_name="service", name="mode"),
        migrations.SeparateDatabaseAndState(
            state_operations=[
                migrations.DeleteModel(name="MissionNotification"),
                migrations.DeleteModel(name="Mission"),
            ],
            database_operations=[],
        ),
    ]
