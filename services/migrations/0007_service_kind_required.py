"""A service names its kind explicitly: no kind is the default."""

import services.models
from django.db import migrations, models


class Migration(migrations.Migration):
    dependencies = [
        ("services", "0006_notice"),
    ]

    operations = [
        migrations.AlterField(
            model_name="service",
            name="kind",
            field=models.CharField(
                help_text="What kind of service this is (services.kinds): what a request sets going, what the user and the vehicles get.",
                max_length=40,
                validators=[services.models._kind_installed],
            ),
        ),
        migrations.AlterField(
            model_name="servicerole",
            name="required",
            field=models.BooleanField(
                default=True,
                help_text="Assigned when the session is requested. Unrequired roles are assigned later by the workflow (e.g. a vehicle chosen once something is found).",
            ),
        ),
    ]
