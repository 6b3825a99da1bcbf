"""Who may use which service."""

from __future__ import annotations

from django.contrib.auth.models import AnonymousUser
from django.db.models import Q, QuerySet

from accounts.users import User
from services.models import Service


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
    return active.filter(Q(grants__user=user) | Q(grants__group__in=user.groups.all())).distinct()


def user_can_use(user: User | AnonymousUser, service: Service) -> bool:
    """True when ``user`` may request ``service``."""
    return services_for_user(user).filter(pk=service.pk).exists()
