"""The rescue's models, taken over from the services app: their tables already exist
(services 0002, 0003), so this changes the migration state only."""

import django.db.models.deletion
from django.db import migrations, models


class Migration(migrations.Migration):
    initial = True

    dependencies = [
        ("services", "0005_service_kinds"),
    ]

    operations = [
        migrations.SeparateDatabaseAndState(
            database_operations=[],
            state_operations=[
                migrations.CreateModel(
                    name="Mission",
                    fields=[
                        (
                            "session",
                            models.OneToOneField(
                                on_delete=django.db.models.deletion.CASCADE,
                                primary_key=True,
                                related_name="mission",
                                serialize=False,
                                to="services.session",
                            ),
                        ),
                        (
                            "state",
                            models.CharField(
                                choices=[
                                    ("waiting_search", "waiting for a search vehicle"),
                                    ("searching", "Searching"),
                                    (
                                        "waiting_delivery",
                                        "person found, waiting for a delivery vehicle",
                                    ),
                                    ("delivering", "Delivering"),
                                    ("returning", "vehicles returning to their stations"),
                                    ("completed", "Completed"),
                                    ("not_found", "search finished without finding the person"),
                                    ("timed_out", "search timed out"),
                                    ("failed", "Failed"),
                                    ("aborted", "Aborted"),
                                ],
                                default="waiting_search",
                                max_length=20,
                            ),
                        ),
                        ("status_text", models.CharField(blank=True, max_length=300)),
                        ("area", models.JSONField()),
                        ("altitude_m", models.FloatField()),
                        ("speed_mps", models.FloatField()),
                        ("spacing_m", models.FloatField(default=0.0)),
                        ("path", models.JSONField(blank=True, default=list)),
                        ("progress", models.IntegerField(default=-1)),
                        ("detection", models.JSONField(blank=True, null=True)),
                        ("detected_at", models.DateTimeField(blank=True, null=True)),
                        ("released_at", models.DateTimeField(blank=True, null=True)),
                        ("search_deadline", models.DateTimeField(blank=True, null=True)),
                        ("search_legs", models.PositiveIntegerField(default=0)),
                        ("updated_at", models.DateTimeField(auto_now=True)),
                    ],
                    options={
                        "db_table": "services_mission",
                    },
                ),
                migrations.CreateModel(
                    name="MissionNotification",
                    fields=[
                        (
                            "id",
                            models.BigAutoField(
                                auto_created=True,
                                primary_key=True,
                                serialize=False,
                                verbose_name="ID",
                            ),
                        ),
                        (
                            "channel",
                            models.CharField(
                                choices=[
                                    ("email", "Email"),
                                    ("webhook", "Webhook"),
                                    ("dashboard", "Dashboard"),
                                ],
                                max_length=10,
                            ),
                        ),
                        ("target", models.CharField(blank=True, max_length=300)),
                        ("payload", models.JSONField()),
                        ("created_at", models.DateTimeField(auto_now_add=True)),
                        ("sent_at", models.DateTimeField(blank=True, null=True)),
                        ("attempts", models.PositiveIntegerField(default=0)),
                        ("claimed_until", models.DateTimeField(blank=True, null=True)),
                        ("last_error", models.CharField(blank=True, max_length=300)),
                        (
                            "mission",
                            models.ForeignKey(
                                on_delete=django.db.models.deletion.CASCADE,
                                related_name="notifications",
                                to="rescue_at_sea.mission",
                            ),
                        ),
                    ],
                    options={
                        "db_table": "services_missionnotification",
                        "constraints": [
                            models.UniqueConstraint(
                                fields=("mission", "channel"), name="one_notice_per_channel"
                            )
                        ],
                    },
                ),
            ],
        ),
    ]
