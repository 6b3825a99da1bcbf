"""The rescue's notices move to the core's (services.Notice): each one is copied over,
sent or not, then the rescue's own table goes."""

from django.db import migrations


def copy_notices(apps, schema_editor):  # type: ignore[no-untyped-def]
    Old = apps.get_model("rescue_at_sea", "MissionNotification")
    Notice = apps.get_model("services", "Notice")
    for old in Old.objects.all():
        payload = dict(old.payload or {})
        message = payload.pop("message", "")
        Notice.objects.get_or_create(
            session_id=old.mission_id,
            channel=old.channel,
            topic="person_in_water",
            defaults={
                "target": old.target if old.channel != "dashboard" else "",
                "level": "bad",
                "subject": "[IoUV rescue] Person in the water",
                "message": message,
                "payload": payload,
                "sent_at": old.sent_at,
                "attempts": old.attempts,
                "claimed_until": old.claimed_until,
                "last_error": old.last_error,
            },
        )


class Migration(migrations.Migration):
    dependencies = [
        ("rescue_at_sea", "0001_initial"),
        ("services", "0006_notice"),
    ]

    operations = [
        migrations.RunPython(copy_notices, migrations.RunPython.noop),
        migrations.DeleteModel(name="MissionNotification"),
    ]
