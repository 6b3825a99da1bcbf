from django.apps import AppConfig


class ServicesConfig(AppConfig):
    name = "services"
    verbose_name = "Services"

    def ready(self) -> None:
        # fleet never imports services: it publishes what agents say as signals, and
        # the supervisor listens here.
        from fleet.signals import (
            agent_acked,
            agent_connected,
            agent_disconnected,
            agent_message,
            agent_welcome,
            vehicle_back,
        )
        from services import supervision

        agent_message.connect(
            supervision.receive_agent_message, dispatch_uid="services.supervision.message"
        )
        agent_connected.connect(
            supervision.receive_agent_connected, dispatch_uid="services.supervision.connected"
        )
        agent_disconnected.connect(
            supervision.receive_agent_disconnected,
            dispatch_uid="services.supervision.disconnected",
        )
        agent_acked.connect(
            supervision.receive_agent_acked, dispatch_uid="services.supervision.acked"
        )
        vehicle_back.connect(
            supervision.receive_vehicle_back, dispatch_uid="services.supervision.back"
        )
        agent_welcome.connect(
            supervision.receive_agent_welcome, dispatch_uid="services.supervision.welcome"
        )
        # The flight records vehicles upload are kept with their sessions.
        from fleet.records import record_keeper_set
        from services.records import record_batch_store

        record_keeper_set(record_batch_store)
        # Celery's workers count their failed tasks where /metrics reads them.
        from celery.signals import task_failure

        from services.metrics import celery_task_failed

        task_failure.connect(celery_task_failed, dispatch_uid="services.metrics.task_failure")
