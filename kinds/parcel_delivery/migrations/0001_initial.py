"""Parcel delivery: the state of each delivery."""

import django.db.models.deletion
import kinds.parcel_delivery.models
from django.db import migrations, models


class Migration(migrations.Migration):

    initial = True

    dependencies = [
        ('services', '0006_notice'),
    ]

    operations = [
        migrations.CreateModel(
            name='Delivery',
            fields=[
                ('session', models.OneToOneField(on_delete=django.db.models.deletion.CASCADE, primary_key=True, related_name='delivery', serialize=False, to='services.session')),
                ('state', models.CharField(choices=[('waiting_carrier', 'waiting for a vehicle'), ('to_pickup', 'on its way to the pickup'), ('to_dropoff', 'parcel on board, on its way to the drop-off'), ('returning', 'delivered; the vehicle is returning'), ('delivered', 'Delivered'), ('cancelled', 'Cancelled'), ('failed', 'Failed')], default='waiting_carrier', max_length=20)),
                ('status_text', models.CharField(blank=True, max_length=300)),
                ('pickup_lat', models.FloatField()),
                ('pickup_lon', models.FloatField()),
                ('dropoff_lat', models.FloatField()),
                ('dropoff_lon', models.FloatField()),
                ('weight_kg', models.FloatField()),
                ('over_water', models.BooleanField(default=False)),
                ('recipient_name', models.CharField(blank=True, max_length=100)),
                ('recipient_email', models.EmailField(blank=True, max_length=254)),
                ('recipient_webhook', models.URLField(blank=True)),
                ('tracking_token', models.CharField(default=kinds.parcel_delivery.models._tracking_token, max_length=40, unique=True)),
                ('handover_lat', models.FloatField(blank=True, null=True)),
                ('handover_lon', models.FloatField(blank=True, null=True)),
                ('loaded_at', models.DateTimeField(blank=True, null=True)),
                ('released_at', models.DateTimeField(blank=True, null=True)),
                ('legs', models.PositiveIntegerField(default=0)),
                ('updated_at', models.DateTimeField(auto_now=True)),
            ],
        ),
    ]
