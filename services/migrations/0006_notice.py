"""Notices: what a session tells people outside it, once per channel (services.notices)."""

import django.db.models.deletion
from django.db import migrations, models


class Migration(migrations.Migration):

    dependencies = [
        ('services', '0005_service_kinds'),
    ]

    operations = [
        migrations.CreateModel(
            name='Notice',
            fields=[
                ('id', models.BigAutoField(auto_created=True, primary_key=True, serialize=False, verbose_name='ID')),
                ('channel', models.CharField(choices=[('email', 'Email'), ('webhook', 'Webhook'), ('dashboard', "monitors' dashboard")], max_length=10)),
                ('topic', models.SlugField(max_length=40)),
                ('target', models.CharField(blank=True, max_length=300)),
                ('level', models.CharField(choices=[('info', 'Info'), ('warn', 'warning'), ('bad', 'alert')], default='info', max_length=5)),
                ('subject', models.CharField(blank=True, max_length=200)),
                ('message', models.TextField()),
                ('payload', models.JSONField(blank=True, default=dict)),
                ('created_at', models.DateTimeField(auto_now_add=True)),
                ('sent_at', models.DateTimeField(blank=True, null=True)),
                ('attempts', models.PositiveIntegerField(default=0)),
                ('claimed_until', models.DateTimeField(blank=True, null=True)),
                ('last_error', models.CharField(blank=True, max_length=300)),
                ('session', models.ForeignKey(on_delete=django.db.models.deletion.CASCADE, related_name='notices', to='services.session')),
            ],
            options={
                'ordering': ['created_at'],
                'constraints': [models.UniqueConstraint(fields=('session', 'channel', 'topic'), name='one_notice_per_topic')],
            },
        ),
    ]
