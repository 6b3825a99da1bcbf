"""Opening a session: the one route every kind takes (:func:`session_open`, from
``ServiceKind.open``, which services.sessions.request.service_request calls for the portal
and the API alike). The grant is checked, the user's live sessions counted against the
service's cap under the user's row lock, and the session recorded; a kind the user drives
has its vehicles reserved (services.sessions.matching) and their tasks signed and owed
(services.sessions.deployment) in the same transaction.
"""

from __future__ import annotations

import uuid
from typing import Any

from django.contrib.auth import get_user_model
from django.db import transaction

from accounts.users import User
from services.kinds import Opened
from services.models import Service, Session
from services.sessions.deployment import DeploymentError, InvalidTaskError, session_tasks_deploy
from services.sessions.grants import user_can_use
from services.sessions.log import event_append, events_staged
from services.sessions.matching import AssignmentError, session_roles_assign
from services.sessions.states import FINAL, session_transition_locked

#: States of a session that holds (or is about to hold) vehicles.
LIVE_STATES = [state for state in Session.State.values if state not in FINAL]


def session_record(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    params: dict[str, Any] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
    pk: Any = None,
    write: bool = True,
) -> Session:
    """A new session recorded in the caller's transaction, without the grant check (the
    caller made it: :func:`session_open`): the cap is counted under the
    user's row lock, the session (``pk`` if given) is recorded and its ``requested``
    event logged. Raises AssignmentError (``over_cap``) before writing anything.

    ``write=False``: the session is not written yet. Its state changes stay on the
    instance (services.sessions.states) and the caller writes it once, as they leave it, with
    :func:`session_write` before its transaction ends (what refers to it, its
    assignments and its log, is checked against it at the commit)."""
    # The user's row is the lock: two requests of one user are counted one after the
    # other, so together they cannot pass the cap. The count is a statement of its own:
    # under READ COMMITTED a statement sees what was committed when it began, and the
    # lock may be waited for; counted in the locking statement, a racing request's
    # session, committed while this one waited, would not be seen.
    list(
        get_user_model().objects.select_for_update().filter(pk=user.pk).values_list("pk", flat=True)
    )
    live = Session.objects.filter(user=user, service=service, state__in=LIVE_STATES).count()
    cap = service.max_sessions_per_user
    if live >= cap:
        raise AssignmentError(
            f"you already have {live} live session{'s' if live != 1 else ''} of "
            f"{service.name!r} (at most {cap}); end one first",
            over_cap=True,
        )
    session = Session(
        service=service,
        user=user,
        target_lat=target[0] if target else None,
        target_lon=target[1] if target else None,
        params=params or {},
        relay=relay,
    )
    if pk is not None:
        session.pk = pk
    if write:
        session.save(force_insert=True)
    event_append(
        session=session,
        kind="requested",
        data={
            "user": user.get_username(),
            "target": list(target) if target else None,
            "relay": relay,
            "preferences": preferences or {},
        },
        locked=True,  # nobody else sees it before this transaction commits
    )
    return session


def session_write(session: Session) -> Session:
    """Write a session :func:`session_record` left unwritten, as it is now."""
    session.save(force_insert=True)
    return session


def service_grant_require(*, user: User, service: Service) -> None:
    """Raises AssignmentError when ``user`` may not use ``service`` (or it is off)."""
    if not service.is_active or not user_can_use(user, service):
        raise AssignmentError(f"you may not use the service {service.name!r}")


def session_open(
    *,
    user: User,
    service: Service,
    target: tuple[float, float] | None = None,
    params: dict[str, Any] | None = None,
    relay: bool = False,
    preferences: dict[str, Any] | None = None,
    deploy: bool = False,
    grant_checked: bool = False,
) -> Opened:
    """Open a session of ``service`` for ``user``: the one way every kind opens one
    (from :meth:`ServiceKind.open <services.kinds.ServiceKind.open>`, which
    services.sessions.request.service_request calls for the portal and the API alike).

    The grant is checked (unless ``grant_checked``: the caller has just checked it), and
    the user's live sessions of the service counted against ``max_sessions_per_user``
    under the user's row lock; the session is recorded with its ``requested`` event.

    ``deploy=False`` (a kind whose workflow finds its vehicles as it goes): that is all,
    in the caller's transaction; ``Opened.task`` is None.

    ``deploy=True`` (a kind the user drives): in one transaction, with the session's log
    written in one go at its end, the service's required roles are reserved
    (``preferences`` narrowing them), every vehicle's signed task is owed to its agent,
    and the controller's user task is returned in ``Opened.task``.

    Raises AssignmentError when the user may not use the service or holds as many live
    sessions of it as it allows (``over_cap``): nothing is recorded. With ``deploy``:
    AssignmentError when a role cannot be filled (the session is recorded as failed,
    no vehicle stays reserved); InvalidTaskError (with ``session``) when the service's
    settings cannot make a valid task: the session is recorded as assigned, then failed
    with that reason, its vehicles released and nothing sent.
    """
    if not grant_checked:
        service_grant_require(user=user, service=service)
    if not deploy:
        with transaction.atomic():
            session = session_record(
                user=user,
                service=service,
                target=target,
                params=params,
                relay=relay,
                preferences=preferences,
            )
        return Opened(session=session)
    refused: AssignmentError | InvalidTaskError | None = None
    pk = uuid.uuid4()
    # The session written once, as the block leaves it (session_record's write).
    with transaction.atomic(), events_staged(session_id=pk) as log:
        session = session_record(
            user=user,
            service=service,
            target=target,
            params=params,
            relay=relay,
            preferences=preferences,
            pk=pk,
            write=False,
        )
        try:
            assignments = session_roles_assign(
                session=session, service=service, target=target, preferences=preferences
            )
            if not assignments:
                raise DeploymentError(f"session {session.pk} has no assigned vehicle")
            # A new session: no earlier task of it can be owed to supersede.
            task = session_tasks_deploy(session=session, assignments=assignments, supersede=False)
        except AssignmentError as exc:
            refused = exc  # the failed session is committed, then the refusal raised
        except InvalidTaskError as exc:
            session_transition_locked(session=session, to=Session.State.FAILED, reason=str(exc))
            exc.session = session
            refused = exc
        session_write(session)
    if refused is not None:
        raise refused
    # A new session: these are all its assignments, and its whole log.
    session.known_assignments, session.known_events = assignments, log
    return Opened(session=session, task=task)
