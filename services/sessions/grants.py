"""Who may use which service."""

from __future__ import annotations

from typing import Any, TypedDict

from django.contrib.auth.models import AnonymousUser, Group
from django.db.models import BooleanField, Exists, OuterRef, Q, QuerySet, Value
from django_stubs_ext import WithAnnotations

from accounts.users import User
from services.models import Service, ServiceGrant


def _granted(user_id: Any) -> Exists:
    """Whether the outer service is granted to the user ``user_id`` or to one of their
    groups."""
    grants = ServiceGrant.objects.filter(service=OuterRef("pk"))
    return Exists(
        grants.filter(Q(user_id=user_id) | Q(group__in=Group.objects.filter(user=user_id)))
    )


class Usable(TypedDict):
    usable: bool


def services_usable(user: User | AnonymousUser) -> QuerySet[WithAnnotations[Service, Usable]]:
    """Active services, each with ``usable``: whether ``user`` may request it, as
    :func:`services_for_user` says. Read together, a service and the user's right to it
    are one query."""
    active = Service.objects.filter(is_active=True)
    if not user.is_authenticated or not (
        user.is_superuser or user.has_perm("services.use_services")
    ):
        return active.annotate(usable=Value(False, output_field=BooleanField()))
    if user.is_superuser:
        return active.annotate(usable=Value(True, output_field=BooleanField()))
    return active.annotate(usable=_granted(user.pk))


def service_usable_get(
    user: User | AnonymousUser, slug: str
) -> WithAnnotations[Service, Usable] | None:
    """The active service ``slug`` with ``usable`` (as :func:`services_usable`), or None."""
    return services_usable(user).filter(slug=slug).first()


def services_for_user(user: User | AnonymousUser) -> QuerySet[Service]:
    """Active services ``user`` may request: granted to them or to one of their groups.

    Needs the ``services.use_services`` permission too (the client role); superusers
    see every active service.
    """
    active = Service.objects.filter(is_active=True)
    if not user.is_authenticated:
        return active.none()
    if user.is_superuser:
        return active
    if not user.has_perm("services.use_services"):
        return active.none()
    return active.filter(_granted(user.pk))


def user_can_use(user: User | AnonymousUser, service: Service) -> bool:
    """True when ``user`` may request ``service``."""
    return services_for_user(user).filter(pk=service.pk).exists()
