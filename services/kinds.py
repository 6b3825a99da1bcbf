"""Service kinds: what a kind of service declares, and the registry the core asks.

A *service kind* (live control, watching, an autonomous search, a delivery, ...) is one
folder under ``kinds/``: a Django app whose ``ready()`` registers one
:class:`ServiceKind`. A ``Service`` row (an offer to users: its limits, roles, grants)
names its kind in ``Service.kind``. The core (assignment, deployment, supervision,
sessions, the portal, the API, the consumers) only ever calls the registry and the
methods below; it never names a kind, and kinds never import each other.

What a kind declares:

* **who drives** (:attr:`ServiceKind.user_drives`): a user controls a vehicle live
  (a controller grant, the connect timeout, the reconnection grace), or the platform
  runs the session (the user watches);
* **how it is requested**: the request fields it reads besides ``params``
  (:attr:`ServiceKind.accepts`), and :meth:`ServiceKind.params_clean`, the one
  validation of its input for both the portal's form and the API; its portal form and
  page (:attr:`ServiceKind.form_class`, :attr:`ServiceKind.request_template`);
* **the user task**: the page the session opens on (:attr:`ServiceKind.session_template`,
  with :meth:`ServiceKind.session_context`) and the grant role it hands the browser;
* **the vehicle tasks**: the missions it deploys (:attr:`ServiceKind.missions`, specs
  of the agent's missions, agents/missions/<name>/spec.py) and the one signed into each
  vehicle's task (:meth:`ServiceKind.vehicle_mission`);
* **the platform task**: :meth:`ServiceKind.open` (what a request sets going), the
  agent events it handles (:attr:`ServiceKind.event_handlers`), what an accepted task
  means (:meth:`ServiceKind.task_accepted`); Celery steps and timers live in its own
  ``tasks.py``;
* **its part of the demo world**: the services it offers there
  (:meth:`ServiceKind.demo_services`) and any rows of its own they need
  (:meth:`ServiceKind.demo_seed`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, ClassVar

from agents.missions.registry import missions as agent_missions

if TYPE_CHECKING:
    from django import forms
    from django.http import HttpRequest

    from accounts.users import User
    from agents.missions.spec import MissionSpec
    from services.models import Assignment, Service, ServiceRole, Session, SessionArtifact
    from services.sessions.deployment import UserTask

#: The request fields, besides ``params``, a kind may read.
REQUEST_FIELDS = frozenset({"target", "relay", "preferences"})


class RequestError(Exception):
    """A request a kind refuses as given; ``field`` names the request field at fault
    (dotted, as the API names it: ``params.area``), ``str()`` says why."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


@dataclasses.dataclass(frozen=True)
class Request:
    """What a user asks of a service, from the portal's form or the API's body."""

    target: tuple[float, float] | None = None
    relay: bool = False
    preferences: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    params: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def given(self) -> set[str]:
        """The request fields (besides ``params``) that say something."""
        given = set()
        if self.target is not None:
            given.add("target")
        if self.relay:
            given.add("relay")
        if self.preferences:
            given.add("preferences")
        return given


@dataclasses.dataclass(frozen=True)
class Opened:
    """A request that went through: the session, and the user task when the user
    drives (the controller page's control URL and grant), else None."""

    session: Session
    task: UserTask | None = None


@dataclasses.dataclass(frozen=True)
class DemoService:
    """A service the demo world offers: the ``Service`` row's fields (``kind`` is
    filled in) and its roles, name -> ``ServiceRole`` fields."""

    fields: Mapping[str, Any]
    roles: Mapping[str, Mapping[str, Any]]


#: An agent event handler: (the reporting vehicle's assignment, the event's data).
EventHandler = Callable[["Assignment", dict[str, Any]], None]


class ServiceKind:
    """Base of every service kind; subclasses set the class attributes and override
    what differs. See the module docstring."""

    #: The registry key, stored in ``Service.kind``.
    name: ClassVar[str]
    #: For people: the admin's choice list, the catalog.
    label: ClassVar[str]
    #: A user controls a vehicle live; otherwise the platform runs the session.
    user_drives: ClassVar[bool] = False
    #: Requested as a session of its own (a kind that only watches others' is not).
    requestable: ClassVar[bool] = True
    #: Request fields besides ``params`` the kind reads; a request giving others is
    #: refused, so nothing a user asks is silently ignored.
    accepts: ClassVar[frozenset[str]] = frozenset()
    #: The portal's request form (it collects the request; :meth:`params_clean`
    #: validates it, as for the API) and its page.
    form_class: ClassVar[type[forms.Form] | None] = None
    request_template: ClassVar[str] = ""
    #: The page a session of this kind opens on.
    session_template: ClassVar[str] = "services/controller.html"
    #: The kind's own URLs (a URLconf module, dotted), included at the site's root.
    urls: ClassVar[str | None] = None
    #: What the catalog's button says.
    entry_label: ClassVar[str] = "Request"
    #: Agent events of this kind's sessions the kind handles (name -> handler); the
    #: core logs the others.
    event_handlers: ClassVar[Mapping[str, EventHandler]] = {}
    #: The agent missions this kind deploys (their specs); :meth:`vehicle_mission`
    #: returns one of these or None.
    missions: ClassVar[tuple[type[MissionSpec], ...]] = ()

    # --- request -------------------------------------------------------------------------
    def params_clean(self, params: Mapping[str, Any]) -> dict[str, Any]:
        """The kind's own request input, validated; raises RequestError naming the
        field (``params.<name>``). Default: free-form, kept with the session."""
        return dict(params)

    def request_from_form(self, form: forms.Form) -> Request:
        """The request a valid portal form stands for (its ``params`` not yet
        cleaned: :meth:`params_clean` does that for both paths)."""
        raise NotImplementedError(f"{self.name} has no portal form")

    def open(self, *, service: Service, user: User, request: Request) -> Opened:
        """Set a request going: reserve, deploy, start the workflow. ``request`` has
        been checked against :attr:`accepts` and its params cleaned.

        Raises services.sessions.matching.AssignmentError (no vehicle, over the user's cap),
        services.sessions.deployment.DeploymentError, or RequestError.
        """
        raise NotImplementedError

    def request_role(self, service: Service) -> ServiceRole | None:
        """The role whose vehicles the request page shows (those available now, and
        where they reach): the service's first required role, else its first."""
        roles = list(service.roles.all())
        candidates = [role for role in roles if role.required] or roles
        return candidates[0] if candidates else None

    def request_map(self, service: Service) -> dict[str, Any] | None:
        """What the request page's map shows (``stations``, the first one where it
        opens, and ``reach``, circles of where the vehicles can go: see
        services.sessions.feasibility.reach_map), or None (this default) for the core's
        map: the vehicles of the whole fleet that could ever serve :meth:`request_role`,
        each from its station on a full battery (services.sessions.feasibility.
        request_map_default; the registry imports nothing of the sessions it is asked
        about)."""
        return None

    def entry_url(self, service: Service) -> str:
        """Where the catalog sends a user who picks ``service``: its request page."""
        from django.urls import reverse

        return reverse("service_request", args=[service.slug])

    # --- the user task -------------------------------------------------------------------
    def grant_role(self, session: Session) -> str:
        """The grant the session's own user gets: ``controller`` where the user
        drives, else ``viewer`` (a viewer's link cannot arm the vehicle's link-loss
        fail-safe, so closing the page does not abort an autonomous mission)."""
        return "controller" if self.user_drives else "viewer"

    def session_context(self, *, request: HttpRequest, session: Session) -> dict[str, Any]:
        """Extra context for :attr:`session_template`."""
        return {}

    def situation(self, session: Session) -> str:
        """What a live session of a kind nobody drives is doing now, in a sentence for
        its spectators ("search-1 searches the area: waypoint 3 of 12 reached"), or ""
        (the core then says that it runs by itself)."""
        return ""

    def session_data(self, session: Session) -> dict[str, Any] | None:
        """The kind's live state of a session as JSON (a mission map...), or None."""
        return None

    # --- the vehicle and platform tasks --------------------------------------------------
    def vehicle_mission(self, *, assignment: Assignment) -> MissionSpec | None:
        """The autonomous mission signed into this vehicle's task (an instance of one of
        :attr:`missions`, built from the kind's recorded state so a re-sent task carries
        the same), or None. Raises MissionError when that state makes no valid one."""
        return None

    def task_accepted(self, *, assignment: Assignment) -> None:
        """A vehicle of one of this kind's sessions accepted its task."""

    def artifact_received(self, *, artifact: SessionArtifact) -> None:
        """A vehicle of one of this kind's sessions uploaded a whole file its mission
        made (a photo; ``artifact.meta`` says what it is), now stored and logged.
        Called after the commit that stored it, once per file; what it does should be
        quick (schedule a step)."""

    # --- the demo world ------------------------------------------------------------------
    def demo_services(self) -> Mapping[str, DemoService]:
        """The services of this kind the demo offers (``manage.py seed_demo``), by
        slug. They may use the demo fleet's names and vocabularies (services.demo)."""
        return {}

    def demo_seed(self) -> None:
        """Write the rows of the kind's own its demo services need; called after the
        demo fleet is seeded, inside the same transaction, and must be idempotent."""


_REGISTRY: dict[str, ServiceKind] = {}


class UnknownKind(LookupError):
    """No kind of that name is installed (its app is not in INSTALLED_APPS)."""


def kind_register(kind: ServiceKind) -> ServiceKind:
    """Make ``kind`` available under its name (call from the kind app's ``ready()``).
    Registering a second kind under a taken name, or a kind declaring a mission no
    agent mission folder provides, is a bug and raises ValueError."""
    installed = {m.spec for m in agent_missions().values()}
    unknown = sorted(spec.__name__ for spec in kind.missions if spec not in installed)
    if unknown:
        raise ValueError(
            f"service kind {kind.name!r} declares missions no agent has: {', '.join(unknown)}"
        )
    existing = _REGISTRY.get(kind.name)
    if existing is not None and type(existing) is not type(kind):
        raise ValueError(f"service kind {kind.name!r} is registered twice")
    _REGISTRY[kind.name] = kind
    return kind


def kind_named(name: str) -> ServiceKind:
    """The kind registered as ``name``; raises UnknownKind."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownKind(f"no service kind {name!r} is installed") from None


def kind_of(service: Service) -> ServiceKind:
    """``service``'s kind; raises UnknownKind."""
    return kind_named(service.kind)


def kinds() -> list[ServiceKind]:
    """Every installed kind, by name."""
    return [_REGISTRY[name] for name in sorted(_REGISTRY)]


def kinds_user_driven() -> list[str]:
    """Names of the kinds whose users drive (for queries over sessions)."""
    return [kind.name for kind in kinds() if kind.user_drives]
