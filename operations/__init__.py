"""What the platform's processes need to run, below every app: group messages after
commit and their relay in embedded mode (:mod:`operations.layer`), the consumers'
dispatch (:mod:`operations.consumers`), the answers while PostgreSQL is away
(:mod:`operations.outages`), liveness and readiness (:mod:`operations.health`), static
files that refuse paths outside their folders (:mod:`operations.static_finders`) and the
garbage collector's tuning (:mod:`operations.collector`).

``iouv`` keeps the project itself: settings, routing, URLs, the ASGI/WSGI entry points,
the server's command and the Celery app.
"""
