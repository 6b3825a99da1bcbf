"""IoUV settings, all read from the environment.

Two modes, chosen by ``DATABASE_URL``:

* **Embedded** (unset, the default): SQLite under ``var/``, an in-memory channel layer
  unless ``REDIS_URL`` is set, Celery on kombu's SQLAlchemy transport over a SQLite file
  so a separate worker process works with no server, and generated secrets kept under
  ``var/``.
  Nothing to install but Python.
* **Production** (``DATABASE_URL`` set, Postgres): ``REDIS_URL`` for the channel layer
  and the Celery broker, ``SECRET_KEY`` (or ``SECRET_KEY_FILE``) required, HTTPS-only
  cookies, HSTS. ``manage.py check --deploy`` is clean with those set.
"""

from __future__ import annotations

import secrets
from datetime import timedelta
from pathlib import Path
from typing import Any

import django
import django_stubs_ext
from csp.constants import NONE, SELF
from django.core.exceptions import ImproperlyConfigured
from redis.asyncio.retry import Retry as RedisRetry
from redis.backoff import ExponentialBackoff

from iouv.csp_sources import csp_origin_of_template
from iouv.env import (
    database_from_url,
    env_bool,
    env_float,
    env_int,
    env_list,
    env_secret,
    env_str,
)

# The admin's and the forms' generic classes take their model as a type argument at
# run time too (admin.ModelAdmin[Station]), as django-stubs declares them.
django_stubs_ext.monkeypatch()

BASE_DIR = Path(__file__).resolve().parent.parent
VAR_DIR = Path(env_str("IOUV_VAR_DIR", str(BASE_DIR / "var")))
VAR_DIR.mkdir(parents=True, exist_ok=True)

DATABASE_URL = env_str("DATABASE_URL")
REDIS_URL = env_str("REDIS_URL")
EMBEDDED = not DATABASE_URL
DEBUG = env_bool("DEBUG", False)
# Generated secrets kept under var/: fine for the embedded demo and for running the
# tests against local Postgres, never for production.
DEV_SECRETS = EMBEDDED or env_bool("IOUV_DEV_SECRETS", False)


def _embedded_secret(filename: str) -> str:
    """A random secret generated once and kept in var/ (embedded mode only)."""
    path = VAR_DIR / filename
    if not path.exists():
        path.write_text(secrets.token_urlsafe(50))
        path.chmod(0o600)
    return path.read_text().strip()


SECRET_KEY = env_secret("SECRET_KEY")
if not SECRET_KEY:
    if not DEV_SECRETS:
        raise ImproperlyConfigured("Set SECRET_KEY or SECRET_KEY_FILE when DATABASE_URL is set")
    SECRET_KEY = _embedded_secret("secret_key")

ALLOWED_HOSTS = env_list("ALLOWED_HOSTS", ["127.0.0.1", "localhost", "[::1]", "testserver"])
CSRF_TRUSTED_ORIGINS = env_list("CSRF_TRUSTED_ORIGINS", [])

# Service kinds (services.kinds): every folder under kinds/ is one, an app of its own,
# so a new kind of service is one folder. IOUV_SERVICE_KINDS (names, comma separated)
# installs only those.
SERVICE_KINDS = env_list("IOUV_SERVICE_KINDS", []) or sorted(
    path.name for path in (BASE_DIR / "kinds").iterdir() if (path / "apps.py").is_file()
)
SERVICE_KIND_APPS = [f"kinds.{name}" for name in SERVICE_KINDS]

INSTALLED_APPS = [
    "django.contrib.admin",
    "django.contrib.auth",
    "django.contrib.contenttypes",
    "django.contrib.sessions",
    "django.contrib.messages",
    "django.contrib.staticfiles",
    "channels",
    # For its templates and vendored Swagger UI assets (/api/v1/docs loads no CDN).
    "ninja",
    "accounts",
    "fleet",
    "services",
    *SERVICE_KIND_APPS,
    # Login lockout (accounts.lockout): its tables of attempts and its admin pages.
    "axes",
]

MIDDLEWARE = [
    "django.middleware.security.SecurityMiddleware",
    # A view that cannot reach the database answers 503 with Retry-After (operations.outages).
    "operations.outages.DatabaseUnavailableMiddleware",
    # Early, so that every page answered below it, error pages included, carries the
    # policy (CONTENT_SECURITY_POLICY).
    "csp.middleware.CSPMiddleware",
    "django.contrib.sessions.middleware.SessionMiddleware",
    "django.middleware.common.CommonMiddleware",
    "django.middleware.csrf.CsrfViewMiddleware",
    "django.contrib.auth.middleware.AuthenticationMiddleware",
    "django.contrib.messages.middleware.MessageMiddleware",
    "django.middleware.clickjacking.XFrameOptionsMiddleware",
    # Last, as django-axes asks: turns a locked-out log-in into its answer (accounts.lockout).
    "axes.middleware.AxesMiddleware",
]

ROOT_URLCONF = "iouv.urls"
ASGI_APPLICATION = "iouv.asgi.application"
WSGI_APPLICATION = None

TEMPLATES = [
    {
        "BACKEND": "django.template.backends.django.DjangoTemplates",
        "DIRS": [BASE_DIR / "templates"],
        "APP_DIRS": True,
        "OPTIONS": {
            "context_processors": [
                "django.template.context_processors.request",
                "django.contrib.auth.context_processors.auth",
                "django.contrib.messages.context_processors.messages",
            ],
        },
    },
]

DATABASES: dict[str, dict[str, Any]]
if EMBEDDED:
    DATABASES = {
        "default": {
            "ENGINE": "django.db.backends.sqlite3",
            "NAME": env_str("SQLITE_PATH", str(VAR_DIR / "iouv.sqlite3")),
            # The worker and the platform write the same file: wait for the lock
            # instead of failing with "database is locked".
            "OPTIONS": {"timeout": 20, "transaction_mode": "IMMEDIATE"},
        }
    }
else:
    DATABASES = {"default": database_from_url(DATABASE_URL)}
    # Django's own pool of connections, one per process (OPTIONS["pool"]: psycopg_pool).
    # Under ASGI Django's connections belong to each request (asgiref's context-local
    # storage), not to a thread that outlives it, and Celery's Django fixup closes a
    # task's connections when it ends: without a pool, every request and every task
    # opened a new connection (a PostgreSQL backend started and torn down for each).
    # DB_POOL_SIZE=0 turns the pool off; connections are then kept for DB_CONN_MAX_AGE
    # seconds where Django can keep them (a gunicorn thread).
    DB_POOL_SIZE = env_int("DB_POOL_SIZE", 16)
    if DB_POOL_SIZE > 0:
        DATABASES["default"]["OPTIONS"]["pool"] = {
            "min_size": 1,
            "max_size": DB_POOL_SIZE,
            # A request waits this long for a connection before it fails, and is
            # answered 503 with Retry-After (operations.outages): while PostgreSQL is away the
            # pool has none to lend, and a client is told so at once, not after a wait.
            "timeout": env_float("DB_POOL_TIMEOUT_S", 1.0),
            # psycopg_pool retries a failed connection with a backoff that doubles for
            # as long as this (its default: 5 minutes), so after a 40 s outage its next
            # try could come half a minute after PostgreSQL was back. Past this it gives
            # the attempt up and the next request that needs a connection starts a new
            # one at once: the pool is back within seconds of the database.
            "reconnect_timeout": env_float("DB_POOL_RECONNECT_S", 5.0),
        }
        DATABASES["default"]["CONN_MAX_AGE"] = 0  # the pool keeps them, not the threads
    else:
        DATABASES["default"]["CONN_MAX_AGE"] = env_int("DB_CONN_MAX_AGE", 60)
    # A connection is checked before use (an empty statement): with the pool, as it is
    # lent (psycopg_pool's check, which Django hands the pool), else when a kept one is
    # reused. After PostgreSQL restarted, or dropped idle connections, the dead ones
    # are replaced instead of failing a request each.
    DATABASES["default"]["CONN_HEALTH_CHECKS"] = True
    # Connecting to a host that does not answer (a lost network, not a refused port)
    # gives up after this many seconds (libpq's minimum is 2) instead of the system's
    # minutes of TCP retries.
    DATABASES["default"]["OPTIONS"].setdefault(
        "connect_timeout", env_int("DB_CONNECT_TIMEOUT_S", 2)
    )
    # A process that goes silent inside a transaction (its machine cut off from the
    # network, a frozen process) would keep its row locks until TCP gave its connection
    # up, hours later: every request writing the same session or vehicle (a grant, a
    # report, a registration) waited behind it. PostgreSQL ends such a connection after
    # this long and its locks go. The platform's transactions are short (no network
    # call inside one), so this is far past any live one. 0 turns it off (a pooler in
    # transaction mode refuses startup options: PgBouncer's idle_transaction_timeout
    # does the same there).
    DB_IDLE_IN_TRANSACTION_S = env_float("DB_IDLE_IN_TRANSACTION_S", 10.0)
    #: libpq's startup option that sets it (the test harness takes it off its own
    #: connections: pytest-django holds a test in one transaction however long it runs).
    DB_IDLE_IN_TRANSACTION_OPTION = (
        f"-c idle_in_transaction_session_timeout={round(DB_IDLE_IN_TRANSACTION_S * 1000)}"
    )
    if DB_IDLE_IN_TRANSACTION_S > 0:
        _startup = DATABASES["default"]["OPTIONS"].get("options", "")
        DATABASES["default"]["OPTIONS"]["options"] = (
            f"{_startup} {DB_IDLE_IN_TRANSACTION_OPTION}".strip()
        )
    # Statements bound and prepared by PostgreSQL: psycopg sends the values apart from
    # the SQL instead of quoting them into it in Python, and a statement a connection
    # has run DB_PREPARE_THRESHOLD times is prepared there, parsed and planned once.
    # The platform's statements are few and repeat (a session's request, end and
    # reports run the same ORM queries with new values), so both cut the process's
    # CPU per statement and PostgreSQL's. A pooler in transaction mode (PgBouncer
    # before 1.21) cannot keep prepared statements: DB_PREPARE_THRESHOLD=0 turns
    # preparing off.
    DATABASES["default"]["OPTIONS"].setdefault("server_side_binding", True)
    _prepare_after = env_int("DB_PREPARE_THRESHOLD", 2)
    DATABASES["default"]["OPTIONS"].setdefault(
        "prepare_threshold", _prepare_after if _prepare_after > 0 else None
    )

DEFAULT_AUTO_FIELD = "django.db.models.BigAutoField"

CHANNEL_LAYERS: dict[str, dict[str, Any]]
if REDIS_URL:
    CHANNEL_LAYERS = {
        "default": {
            "BACKEND": "channels_redis.core.RedisChannelLayer",
            "CONFIG": {
                # Each host's keys go to redis-py's connection pool, as its from_url
                # takes them.
                "hosts": [
                    {
                        "address": REDIS_URL,
                        # channels_redis blocks 5 s in BZPOPMIN waiting for messages:
                        # a read may wait longer than that without failing.
                        "socket_timeout": 10,
                        "socket_connect_timeout": 2,
                        # redis-py's pool fails a call past this many connections (its
                        # default is 100): a thousand agents reconnecting at once each
                        # join their group while pushes and relayed frames go on.
                        "max_connections": env_int("REDIS_MAX_CONNECTIONS", 2000),
                        # A lost connection is retried, after 0.1 s, 0.2 s, 0.4 s, then
                        # every 0.5 s for about 15 s: a restart or a fail-over of Redis
                        # is waited out instead of ending every consumer of the process
                        # (a receive that fails ends its consumer and closes its
                        # socket). Past that, the sockets close and their clients
                        # connect again, as after a platform restart.
                        "retry": RedisRetry(ExponentialBackoff(cap=0.5, base=0.05), 30),
                    }
                ],
                "prefix": env_str("CHANNELS_PREFIX", "iouv"),
                "capacity": 1000,
                "expiry": 30,
                # Members are added again every minute or so while their consumer
                # lives, and at once after Redis restarted (fleet.memberships): one left
                # by a process that died is gone in three, not in channels_redis's
                # default day.
                "group_expiry": 180,
            },
        }
    }
else:
    CHANNEL_LAYERS = {"default": {"BACKEND": "channels.layers.InMemoryChannelLayer"}}

# Django's cache: the login lockout's and the rate limits' counters (services.web.throttle),
# in Redis when there is one, so that every platform process counts together; in the
# process's memory otherwise (embedded mode has one platform process).
CACHES: dict[str, dict[str, Any]]
if REDIS_URL:
    CACHES = {
        "default": {
            "BACKEND": "django.core.cache.backends.redis.RedisCache",
            "LOCATION": REDIS_URL,
            "KEY_PREFIX": env_str("CHANNELS_PREFIX", "iouv") + ":cache",
            # A Redis that does not answer fails a limit's check in a second, not in
            # the system's TCP timeouts (services.web.throttle then lets the call through).
            "OPTIONS": {"socket_connect_timeout": 1, "socket_timeout": 1},
        }
    }
else:
    CACHES = {"default": {"BACKEND": "django.core.cache.backends.locmem.LocMemCache"}}

# django-axes' lockout check first (accounts.lockout: a locked-out address or account is
# refused before its password is hashed), then Django's ModelBackend with a user's
# permissions read in one query (accounts.backends).
AUTHENTICATION_BACKENDS = ["accounts.lockout.LoginLockoutBackend", "accounts.backends.RoleBackend"]

AUTH_PASSWORD_VALIDATORS = [
    {"NAME": "django.contrib.auth.password_validation.UserAttributeSimilarityValidator"},
    {"NAME": "django.contrib.auth.password_validation.MinimumLengthValidator"},
    {"NAME": "django.contrib.auth.password_validation.CommonPasswordValidator"},
    {"NAME": "django.contrib.auth.password_validation.NumericPasswordValidator"},
]
if env_bool("IOUV_FAST_PASSWORD_HASHER", False):
    # Tests only: a fast hash, shared with the platform processes the tests start.
    PASSWORD_HASHERS = [
        "django.contrib.auth.hashers.MD5PasswordHasher",
        "django.contrib.auth.hashers.PBKDF2PasswordHasher",
    ]
LOGIN_URL = "login"
LOGIN_REDIRECT_URL = "/"
LOGOUT_REDIRECT_URL = "login"

LANGUAGE_CODE = "en-us"
TIME_ZONE = "UTC"
USE_I18N = True
USE_TZ = True

STATIC_URL = "static/"
STATICFILES_DIRS = [BASE_DIR / "static"]
# Django's finders, with a path that leaves their folders (/static/../..) not found (404)
# instead of an error (operations.static_finders).
STATICFILES_FINDERS = [
    "operations.static_finders.FileSystemFinder",
    "operations.static_finders.AppDirectoriesFinder",
]
STATIC_ROOT = Path(env_str("STATIC_ROOT", str(VAR_DIR / "static")))
# The platform serves /static/ itself (iouv.asgi) unless a proxy in front does it.
SERVE_STATIC = env_bool("SERVE_STATIC", True)

# --- Security: strict unless embedded -------------------------------------------------
SECURE_CONTENT_TYPE_NOSNIFF = True
X_FRAME_OPTIONS = "DENY"
SESSION_COOKIE_SECURE = env_bool("SECURE_COOKIES", not EMBEDDED)
CSRF_COOKIE_SECURE = SESSION_COOKIE_SECURE
SECURE_SSL_REDIRECT = env_bool("SECURE_SSL_REDIRECT", not EMBEDDED)
# Health checks reach the processes behind the TLS proxy over plain http: a redirect to
# https would read as "down".
SECURE_REDIRECT_EXEMPT = [r"^(healthz|readyz|metrics)$"]
SECURE_HSTS_SECONDS = env_int("SECURE_HSTS_SECONDS", 0 if EMBEDDED else 31_536_000)
SECURE_HSTS_INCLUDE_SUBDOMAINS = not EMBEDDED
SECURE_HSTS_PRELOAD = not EMBEDDED
# Behind nginx: its X-Forwarded-Proto says whether the request came over TLS, and the last
# entry of its X-Forwarded-For is the client's address (accounts.addresses).
BEHIND_PROXY = env_bool("BEHIND_PROXY", False)
if BEHIND_PROXY:
    SECURE_PROXY_SSL_HEADER = ("HTTP_X_FORWARDED_PROTO", "https")

# --- Celery ----------------------------------------------------------------------------
if REDIS_URL:
    CELERY_BROKER_URL = REDIS_URL
    CELERY_BROKER_TRANSPORT_OPTIONS: dict[str, object] = {
        # A task whose worker died unacknowledged (acks_late) is delivered again after
        # this long; workflow steps are idempotent, so a second run changes nothing.
        "visibility_timeout": env_int("CELERY_VISIBILITY_TIMEOUT_S", 3600),
        # A Redis host that stops answering without closing the sockets (a lost
        # network, not a crash) must not hang the worker or beat: connecting and each
        # reply have a deadline, and a connection idle for health_check_interval is
        # checked (a PING; a BRPOP left without its reply is dropped). Redis has no
        # heartbeats (broker_heartbeat is AMQP's); these checks stand in for them.
        "socket_connect_timeout": 5,
        "socket_timeout": 10,
        "health_check_interval": 10,
    }
else:
    # kombu's SQLAlchemy transport on a SQLite file of its own: the platform and a
    # separate worker process share a queue with no server to install, and a message is
    # a row, written and taken in transactions. (kombu's filesystem transport creates a
    # message's file before writing it: a worker polling the folder could take it
    # empty, lose the message and stop on the empty JSON.)
    CELERY_BROKER_URL = f"sqla+sqlite:///{VAR_DIR / 'celery-broker.sqlite3'}"
CELERY_TASK_ACKS_LATE = True
CELERY_TASK_REJECT_ON_WORKER_LOST = True
CELERY_WORKER_PREFETCH_MULTIPLIER = 1
# A worker runs its tasks on threads, all borrowing from the process's pool of database
# connections. Celery's Django fixup hands a task's connection back when the task ends,
# and the next task borrows it again; in a prefork worker the fixup closes the child's
# whole pool after every task instead, so each task started a PostgreSQL backend of its
# own. The tasks wait on PostgreSQL and Redis, not on the CPU. Keep a worker's
# --concurrency at most DB_POOL_SIZE.
CELERY_WORKER_POOL = "threads"
CELERY_TASK_IGNORE_RESULT = True
CELERY_TASK_ALWAYS_EAGER = env_bool("CELERY_TASK_ALWAYS_EAGER", False)
CELERY_BROKER_CONNECTION_RETRY_ON_STARTUP = True
# The worker and its beat reconnect for as long as the broker is away; Celery's default
# gives up after 100 attempts (some 45 minutes) and stops the worker.
CELERY_BROKER_CONNECTION_MAX_RETRIES = None
# A task running when the broker goes away finishes its work: its state is in the
# database. Only its acknowledgement may be lost, and then it runs once more after the
# visibility timeout, changing nothing. Cancelling it (Celery 6's default) would throw
# the work away and still wait for that timeout.
CELERY_WORKER_CANCEL_LONG_RUNNING_TASKS_ON_CONNECTION_LOSS = False

# --- IoUV ------------------------------------------------------------------------------
# The platform's Ed25519 key that signs vehicle tasks and user grants. Agents hold only
# the public half. PEM in IOUV_SIGNING_KEY / IOUV_SIGNING_KEY_FILE; embedded mode makes one.
IOUV_SIGNING_KEY = env_secret("IOUV_SIGNING_KEY")
IOUV_SIGNING_KEY_PATH = VAR_DIR / "platform_signing_key.pem"
if not IOUV_SIGNING_KEY and not DEV_SECRETS:
    raise ImproperlyConfigured("Set IOUV_SIGNING_KEY or IOUV_SIGNING_KEY_FILE in production")
# During a key rotation: the previous keys' public PEMs (one or more blocks), still
# accepted and published in /.well-known/jwks.json until their tokens have expired.
IOUV_SIGNING_PREVIOUS_KEYS = env_secret("IOUV_SIGNING_PREVIOUS_KEYS")
# A vehicle is offline when no heartbeat arrived for this long.
IOUV_OFFLINE_AFTER_S = env_float("IOUV_OFFLINE_AFTER_S", 6.0)
IOUV_HEARTBEAT_INTERVAL_S = env_float("IOUV_HEARTBEAT_INTERVAL_S", 2.0)
# With Redis, heartbeats go to Redis (fleet.liveness) under this key prefix, and the
# vehicle's row is written only when its state changes: a status, online or offline,
# the battery by this many percentage points, the position by this many metres.
IOUV_LIVENESS_PREFIX = env_str("IOUV_LIVENESS_PREFIX", env_str("CHANNELS_PREFIX", "iouv") + ":live")
IOUV_LIVENESS_BATTERY_STEP_PCT = env_float("IOUV_LIVENESS_BATTERY_STEP_PCT", 1.0)
IOUV_LIVENESS_POSITION_STEP_M = env_float("IOUV_LIVENESS_POSITION_STEP_M", 10.0)
# How often a monitor's live fleet view is brought up to date with what the vehicles
# last reported (last heard, battery, position), in seconds.
IOUV_FLEET_FEED_LIVE_S = env_float("IOUV_FLEET_FEED_LIVE_S", 1.0)
# How long a user grant stays valid; the platform issues a fresh one on reconnect.
IOUV_GRANT_TTL_S = env_int("IOUV_GRANT_TTL_S", 300)
# A vehicle task's delivery deadline (its ``exp``): the agent refuses it after this.
IOUV_TASK_TTL_S = env_int("IOUV_TASK_TTL_S", 60)
# An uplink that has not sent ``hello`` after this long is closed.
IOUV_HELLO_TIMEOUT_S = env_float("IOUV_HELLO_TIMEOUT_S", 5.0)
# After a fail-safe or the controller leaving, how long the user has to come back (a
# new connection, or input again on the socket it kept) before the session ends.
IOUV_RECONNECT_GRACE_S = env_int("IOUV_RECONNECT_GRACE_S", 30)
# A session of a user-driven service that nobody connected to this long after its
# vehicle was reserved ends, so a user who asked and left holds no vehicle.
IOUV_CONNECT_TIMEOUT_S = env_float("IOUV_CONNECT_TIMEOUT_S", 120.0)
# A user-driven session whose vehicle has been offline this long ends: the platform can
# no longer supervise it. The vehicle stays offline, not free, until its agent is back.
IOUV_VEHICLE_LOST_S = env_float("IOUV_VEHICLE_LOST_S", IOUV_OFFLINE_AFTER_S)
# Each platform process serving agent uplinks says it is alive this often (fleet.servers):
# while it is gone, the silence of the vehicles it served is the platform's, not theirs.
IOUV_UPLINK_SERVER_BEAT_S = env_float("IOUV_UPLINK_SERVER_BEAT_S", 1.0)
# After the platform (or the process holding its uplink) was away, how long an agent may
# take to come back before its silence counts again: the agents' longest reconnect
# backoff (agents.config: reconnect_max_s).
IOUV_AGENT_RECONNECT_S = env_float("IOUV_AGENT_RECONNECT_S", 30.0)
# How often the supervisor's timers run (Celery beat), in seconds.
IOUV_SUPERVISION_TICK_S = env_float("IOUV_SUPERVISION_TICK_S", 2.0)
# More than this many commands refused for safety reasons within the window revokes
# the session.
IOUV_UNSAFE_REFUSALS_MAX = env_int("IOUV_UNSAFE_REFUSALS_MAX", 5)
IOUV_UNSAFE_REFUSALS_WINDOW_S = env_float("IOUV_UNSAFE_REFUSALS_WINDOW_S", 10.0)
# Flight records (services.records.keeping) older than this many days are deleted by the
# daily sweep; 0 keeps them until an admin deletes them.
IOUV_RECORD_RETENTION_DAYS = env_int("IOUV_RECORD_RETENTION_DAYS", 90)

# Net allocations between two collections of the garbage collector's youngest
# generation in a platform process (Python's default: 700; 0 keeps it). See
# operations.collector: a request's objects then die young instead of filling the oldest
# generation, whose full collections stop the whole process.
IOUV_GC_YOUNG_THRESHOLD = env_int("IOUV_GC_YOUNG_THRESHOLD", 10_000)

# Embedded mode: a worker process pushes through the database to the ASGI process.
IOUV_LAYER_RELAY = env_bool("IOUV_LAYER_RELAY", True)

# Autonomous workflows (services.sessions.workflow): how long a vehicle of a mission may be
# silent before another takes over, the battery level at which it is replaced, and how
# often the workflows' timers run. A kind's own settings are read by the kind.
IOUV_MISSION_OFFLINE_GRACE_S = env_float("IOUV_MISSION_OFFLINE_GRACE_S", 10.0)
# A silent vehicle whose autopilot flies the mission by itself (its agent said so) is
# waited for as long as its agent said the mission may take, at most this (0: never
# waited for: a silent vehicle is taken for lost).
IOUV_MISSION_FLYING_ALONE_MAX_S = env_float("IOUV_MISSION_FLYING_ALONE_MAX_S", 900.0)
IOUV_MISSION_LOW_BATTERY_PCT = env_float("IOUV_MISSION_LOW_BATTERY_PCT", 25.0)
IOUV_MISSION_TICK_S = env_float("IOUV_MISSION_TICK_S", 2.0)
# Map tiles for the maps, e.g. "https://tile.openstreetmap.org/{z}/{x}/{y}.png"
# (mind the tile server's usage policy). Empty: no tiles, the map draws a grid.
IOUV_MAP_TILES_URL = env_str("IOUV_MAP_TILES_URL", "")
# Where people reach the portal from outside (links in e-mails and notices).
IOUV_PUBLIC_URL = env_str("IOUV_PUBLIC_URL", "http://127.0.0.1:8000")
# Notices' webhooks (services.sessions.notices): how long one delivery attempt may take.
IOUV_WEBHOOK_TIMEOUT_S = env_float("IOUV_WEBHOOK_TIMEOUT_S", 5.0)

# --- Abuse: login lockout and rate limits -----------------------------------------------
# django-axes (accounts.lockout): this many failed log-ins from one address, or naming one
# account, lock log-ins from that address or for that account for the cool-off, the right
# password included; a successful log-in clears the address's and account's failures.
AXES_FAILURE_LIMIT = env_int("IOUV_LOGIN_FAILURE_LIMIT", 10)
AXES_COOLOFF_TIME = timedelta(seconds=env_int("IOUV_LOGIN_COOLOFF_S", 900))
AXES_LOCKOUT_PARAMETERS = ["ip_address", "username"]
AXES_RESET_ON_SUCCESS = True
AXES_CLIENT_IP_CALLABLE = "accounts.addresses.client_address"
AXES_LOCKOUT_CALLABLE = "accounts.lockout.login_locked_out"
# One line per failed or locked-out attempt, none per success.
AXES_VERBOSE = False
# Budgets of the actions services.web.throttle limits, "N/<window>" per user and per client
# address ("" or "off": none). IOUV_RATE_<ACTION>="<per user>,<per address>".
IOUV_RATE_LIMITS: dict[str, dict[str, str]] = {}
for _action, _default in {
    "session_request": ["20/m", "60/m"],
    "grant": ["60/m", "240/m"],
    "webrtc_offer": ["30/m", "120/m"],
}.items():
    _per_user, _per_address = [*env_list(f"IOUV_RATE_{_action.upper()}", _default), "off"][:2]
    IOUV_RATE_LIMITS[_action] = {"user": _per_user, "address": _per_address}
# django-ratelimit's switch: IOUV_RATE_LIMITS=0 turns every budget off (benchmarks).
RATELIMIT_ENABLE = env_bool("IOUV_RATE_LIMITS", True)
# /metrics for Prometheus (services.supervision.metrics): with a token, scrapes must send it as a
# bearer token; without one, only clients on the platform's own machine are answered.
IOUV_METRICS_TOKEN = env_secret("IOUV_METRICS_TOKEN")
# --- Faults: what clients are told while a server the platform needs is away -----------
# The Retry-After of a 503 answered while PostgreSQL cannot be reached (operations.outages).
IOUV_RETRY_AFTER_S = env_int("IOUV_RETRY_AFTER_S", 5)

# --- WebRTC: ICE servers handed to users and vehicles (services.sessions.ice) ---------------
# STUN finds a peer's public address behind NAT; TURN (coturn) relays when no direct
# path exists. TURN credentials are minted per session from the secret coturn shares
# (``static-auth-secret``), valid IOUV_TURN_TTL_S. None configured: WebRTC only finds
# peers on a shared network, and the relay over the platform carries the rest.
IOUV_STUN_URLS = env_list("IOUV_STUN_URLS", [])
IOUV_TURN_URLS = env_list("IOUV_TURN_URLS", [])
IOUV_TURN_SECRET = env_secret("IOUV_TURN_SECRET")
IOUV_TURN_TTL_S = env_int("IOUV_TURN_TTL_S", 3600)

# --- The SFU (Janus VideoRoom) that serves spectators and records (services.sfu) -------
# Unset (the embedded demo): spectators connect to the vehicle itself, within its cap.
# IOUV_JANUS_URL: Janus's HTTP API as the platform reaches it (http://127.0.0.1:8088/janus);
# IOUV_JANUS_PUBLIC_URL: its WebSocket API as browsers and vehicles reach it
# (wss://example.org/janus-ws/). The two secrets are Janus's token_auth_secret and the
# VideoRoom plugin's admin_key (docs/video.md, "The SFU"): from the environment or a file.
IOUV_JANUS_URL = env_str("IOUV_JANUS_URL", "")
IOUV_JANUS_PUBLIC_URL = env_str("IOUV_JANUS_PUBLIC_URL", "")
IOUV_JANUS_TOKEN_SECRET = env_secret("IOUV_JANUS_TOKEN_SECRET")
IOUV_JANUS_ADMIN_KEY = env_secret("IOUV_JANUS_ADMIN_KEY")
# Where Janus writes each session's recording (a folder per session); the Celery worker
# converts them there. Empty: nothing is recorded.
IOUV_JANUS_REC_DIR = env_str("IOUV_JANUS_REC_DIR", str(VAR_DIR / "janus-recordings"))
# How long a Janus token (a spectator's, the vehicle's) stays valid: Janus checks it on
# every request of the session, keepalives included, so it must outlast the watching.
IOUV_JANUS_TOKEN_TTL_S = env_int("IOUV_JANUS_TOKEN_TTL_S", 12 * 3600)
# How often the worker makes again the rooms a restarted Janus lost (live sessions only).
IOUV_JANUS_ROOMS_CHECK_S = env_float("IOUV_JANUS_ROOMS_CHECK_S", 15.0)

# --- Content-Security-Policy (django-csp, on every response) ------------------------------
# Scripts and styles come only from the platform's static files (Leaflet is vendored
# there); pages hold no inline code, so neither needs 'unsafe-inline'. The controller
# opens a WebSocket straight to the vehicle's agent (ws://host:port/ of any vehicle),
# hence ws: and wss: in connect-src. WebRTC video reaches <video> as a MediaStream
# (srcObject), which no fetch directive governs. Map tiles come from the tile server in
# IOUV_MAP_TILES_URL; Leaflet blanks a cancelled tile with a data: image.
_MAP_TILES_SOURCE = csp_origin_of_template(IOUV_MAP_TILES_URL, setting="IOUV_MAP_TILES_URL")
CONTENT_SECURITY_POLICY = {
    "DIRECTIVES": {
        "default-src": [SELF],
        "script-src": [SELF],
        "style-src": [SELF],
        "img-src": [SELF, "data:", *([_MAP_TILES_SOURCE] if _MAP_TILES_SOURCE else [])],
        "connect-src": [SELF, "ws:", "wss:"],
        "object-src": [NONE],
        "base-uri": [NONE],
        "form-action": [SELF],
        "frame-ancestors": [NONE],
    }
}

# Where e-mail goes (the rescue team's notices): EMAIL_BACKEND, with the file backend's
# folder or the SMTP server's address and account. Django 6.1 takes these as MAILERS and
# deprecates its EMAIL_* settings (gone in Django 7); 5.2 knows only those.
_MAIL_BACKEND = env_str("EMAIL_BACKEND", "django.core.mail.backends.console.EmailBackend")
_MAIL_FILE_PATH = env_str("EMAIL_FILE_PATH", str(VAR_DIR / "mail"))
_SMTP: dict[str, Any] = {
    "host": env_str("EMAIL_HOST", "localhost"),
    "port": env_int("EMAIL_PORT", 25),
    "username": env_str("EMAIL_HOST_USER"),
    "password": env_secret("EMAIL_HOST_PASSWORD"),
    "use_tls": env_bool("EMAIL_USE_TLS", False),
    "timeout": env_float("EMAIL_TIMEOUT_S", 10.0),
}
if django.VERSION >= (6, 1):
    _MAIL_OPTIONS: dict[str, Any] = {}
    if _MAIL_BACKEND.endswith(".filebased.EmailBackend"):
        _MAIL_OPTIONS = {"file_path": _MAIL_FILE_PATH}
    elif _MAIL_BACKEND.endswith(".smtp.EmailBackend"):
        _MAIL_OPTIONS = _SMTP
    MAILERS = {"default": {"BACKEND": _MAIL_BACKEND, "OPTIONS": _MAIL_OPTIONS}}
else:
    EMAIL_BACKEND = _MAIL_BACKEND
    EMAIL_FILE_PATH = _MAIL_FILE_PATH
    EMAIL_HOST, EMAIL_PORT = _SMTP["host"], _SMTP["port"]
    EMAIL_HOST_USER, EMAIL_HOST_PASSWORD = _SMTP["username"], _SMTP["password"]
    EMAIL_USE_TLS, EMAIL_TIMEOUT = _SMTP["use_tls"], _SMTP["timeout"]
DEFAULT_FROM_EMAIL = env_str("DEFAULT_FROM_EMAIL", "iouv@localhost")

LOGGING = {
    "version": 1,
    "disable_existing_loggers": False,
    "formatters": {"plain": {"format": "%(asctime)s %(levelname)s %(name)s: %(message)s"}},
    # An error that is the database being away is one line, not a traceback each time
    # (operations.outages).
    "filters": {"database_away": {"()": "operations.outages.DatabaseUnavailableLogFilter"}},
    "handlers": {
        "console": {
            "class": "logging.StreamHandler",
            "formatter": "plain",
            "filters": ["database_away"],
        }
    },
    "root": {"handlers": ["console"], "level": env_str("LOG_LEVEL", "INFO")},
    # The servers' lines for each socket opened or closed (daphne's, uvicorn's): a busy
    # process's log would be little else. Their warnings and errors still show.
    "loggers": {
        "django.channels.server": {"level": "WARNING"},
        "uvicorn.error": {"level": "WARNING"},
        # django-axes says INFO for every log-in it sees; its warnings (repeated
        # failures, a lockout) still show.
        "axes": {"level": "WARNING"},
    },
}
