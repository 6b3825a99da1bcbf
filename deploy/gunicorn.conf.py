"""gunicorn's settings for the platform's HTTP processes (``iouv-web@.service``):
``gunicorn -c deploy/gunicorn.conf.py --bind 127.0.0.1:8001 iouv.wsgi:application``.

Each process is a master and ``IOUV_WEB_WORKERS`` worker processes, each with
``IOUV_WEB_THREADS`` threads (gthread): Django's views are synchronous and mostly wait
on PostgreSQL, so a few threads keep a process busy, and several processes use every
core. The values are gunicorn's public settings; see docs/operations.md.
"""

import multiprocessing
import os

#: Worker processes: one a core is enough with threads (IOUV_WEB_WORKERS overrides).
workers = int(os.environ.get("IOUV_WEB_WORKERS", multiprocessing.cpu_count()))
worker_class = "gthread"
threads = int(os.environ.get("IOUV_WEB_THREADS", 4))
# A worker is recycled after this many requests (spread, so they do not all go at once):
# whatever a long life accumulates (fragmented memory) goes with it.
max_requests = 5000
max_requests_jitter = 500
# nginx keeps idle connections to the upstream for 60 s: gunicorn keeps them longer, so
# it is never the side closing one while nginx sends a request on it.
keepalive = 75
# A request running longer than this is a stuck worker: it is killed and replaced.
timeout = 30
# On SIGTERM (a stop) or SIGHUP (a reload: new workers first), requests in progress get
# this long to finish.
graceful_timeout = 20
# The application is loaded by each worker, so a reload (SIGHUP) picks up new code.
preload_app = False
# Request heads: nginx refuses what is over its own limits (a line over 8 KiB,
# deploy/nginx/iouv.conf); these take every line it passes (8190 is gunicorn's largest
# request line) and answer 431 to more than 100 header fields, which nginx does not count.
limit_request_line = 8190
limit_request_field_size = 8190
limit_request_fields = 100
# nginx is the only client: it sets X-Forwarded-Proto, which Django reads when
# BEHIND_PROXY=1; gunicorn itself trusts nothing from the request.
forwarded_allow_ips = ""
accesslog = None
errorlog = "-"
loglevel = "info"
proc_name = "iouv-web"
# gunicorn 25.1+ opens a control socket for gunicornc at one path per user
# (~/.gunicorn/gunicorn.ctl): the machine's several HTTP processes (iouv-web@1, @2...)
# would take it from one another, and the first to stop would remove it under the
# others. Nothing here uses gunicornc; systemd's signals do what it would.
control_socket_disable = True


def child_exit(server: object, worker: object) -> None:
    """A worker process ended: with prometheus-client's multiprocess mode (the unit
    sets ``PROMETHEUS_MULTIPROC_DIR``), its live gauges stop counting
    (services.supervision.metrics)."""
    if os.environ.get("PROMETHEUS_MULTIPROC_DIR"):
        from prometheus_client import multiprocess

        multiprocess.mark_process_dead(worker.pid)  # type: ignore[attr-defined]
