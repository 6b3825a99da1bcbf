from django.apps import AppConfig


class ServicesConfig(AppConfig):
    name = "services"
    verbose_name = "Services"

    def ready(self) -> None:
        # fleet never imports services: its uplink tells the one listener registered
        # here what vehicles say, and the supervisor answers.
        from fleet.vehicle_events import vehicle_events_set
        from services.supervision.reports import Supervisor

        vehicle_events_set(Supervisor())
        # The flight records vehicles upload are kept with their sessions.
        from fleet.records import record_keeper_set
        from services.records.keeping import record_batch_store

        record_keeper_set(record_batch_store)
        # And the files missions upload (their photos).
        from fleet.artifacts import artifact_keeper_set
        from services.records.artifacts import artifact_chunk_store

        artifact_keeper_set(artifact_chunk_store)
        # Celery's workers count their failed tasks where /metrics reads them.
        from celery.signals import task_failure

        from services.supervision.metrics import celery_task_failed

        task_failure.connect(celery_task_failed, dispatch_uid="services.metrics.task_failure")
