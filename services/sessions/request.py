"""Requesting a service: the one path the portal and the API both take.

The portal's form and the API's body each become a :class:`~services.kinds.Request`;
:func:`service_request` checks it against the service and its kind and lets the kind
set it going. A request is checked in the same order whichever way it came, so a user
meets the same refusals, in the same words, on the page and through the API.
"""

from __future__ import annotations

from accounts.users import User
from services.kinds import Opened, Request, RequestError, UnknownKind, kind_of
from services.models import Service
from services.sessions.grants import user_can_use
from services.sessions.matching import AssignmentError


def service_request(
    *, user: User, service: Service, request: Request, usable: bool | None = None
) -> Opened:
    """Open a session of ``service`` for ``user`` as ``request`` asks. ``usable``:
    whether the user may use the service, when the caller read it with the service
    (services.sessions.grants.services_usable); None: asked here.

    Raises AssignmentError when the user may not use the service (``session`` None),
    holds as many live sessions of it as it allows (``over_cap``) or no vehicle fits
    (the failed session recorded); RequestError naming the field at fault (a field the
    kind does not read, invalid params, a kind that is not requested this way or not
    installed); services.sessions.deployment.DeploymentError when deploying failed.
    """
    if usable is None:
        usable = service.is_active and user_can_use(user, service)
    if not usable:
        raise AssignmentError(f"you may not use the service {service.name!r}")
    try:
        kind = kind_of(service)
    except UnknownKind:
        raise RequestError(
            f"{service.name!r} cannot be requested: its kind is not installed", field="service"
        ) from None
    if not kind.requestable:
        raise RequestError(f"{service.name!r} is not requested as a session", field="service")
    refused = sorted(request.given() - kind.accepts)
    if refused:
        raise RequestError(f"{kind.label} does not take {refused[0]}", field=refused[0])
    cleaned = Request(
        target=request.target,
        relay=request.relay,
        preferences=request.preferences,
        params=kind.params_clean(request.params),
    )
    return kind.open(service=service, user=user, request=cleaned)
