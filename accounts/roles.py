"""Roles are Django groups carrying permissions; a user may hold several.

* client   - uses the services their grants allow
* monitor  - watches the fleet and every session, can stop a session
* operator - station staff: puts vehicles in and out of service
* admin    - everything

Permissions are named by string ("app_label.codename") so this module does not import
the apps that define them (accounts sits below fleet and services).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from django.contrib.auth.models import AnonymousUser, Group, Permission
from django.db import transaction

from accounts.users import User

CLIENT = "client"
MONITOR = "monitor"
OPERATOR = "operator"
ADMIN = "admin"
ROLES = (CLIENT, MONITOR, OPERATOR, ADMIN)

ROLE_PERMISSIONS: dict[str, tuple[str, ...]] = {
    CLIENT: ("services.use_services", "services.view_service"),
    MONITOR: (
        "fleet.view_fleet",
        "fleet.view_station",
        "fleet.view_vehicletype",
        "fleet.view_vehicle",
        "services.view_service",
        "services.view_session",
        "services.view_sessionevent",
        "services.view_assignment",
        "services.stop_session",
    ),
    OPERATOR: (
        "fleet.view_fleet",
        "fleet.view_station",
        "fleet.view_vehicletype",
        "fleet.view_vehicle",
        "fleet.change_vehicle",
        "fleet.set_maintenance",
    ),
    ADMIN: (),  # every permission, filled in by roles_ensure
}
# Roles whose holders work in the Django admin.
STAFF_ROLES = {MONITOR, OPERATOR, ADMIN}


def _permissions(names: Iterable[str]) -> list[Permission]:
    found = []
    for name in names:
        app_label, codename = name.split(".", 1)
        perm = Permission.objects.filter(
            content_type__app_label=app_label, codename=codename
        ).first()
        if perm is not None:  # absent until that app has migrated
            found.append(perm)
    return found


def roles_ensure() -> dict[str, Group]:
    """Create the role groups and give each its permissions. Idempotent."""
    groups = {}
    with transaction.atomic():
        for role in ROLES:
            group, _ = Group.objects.get_or_create(name=role)
            perms = (
                list(Permission.objects.all())
                if role == ADMIN
                else _permissions(ROLE_PERMISSIONS[role])
            )
            group.permissions.set(perms)
            groups[role] = group
    return groups


def roles_ensure_on_migrate(**kwargs: Any) -> None:
    """post_migrate receiver: keep the role groups in step with the permissions."""
    roles_ensure()


def user_set_roles(*, user: User, roles: Iterable[str]) -> None:
    """Give ``user`` exactly ``roles``; staff roles also open the Django admin.

    Raises ValueError for a name that is not a role.
    """
    wanted = set(roles)
    unknown = wanted - set(ROLES)
    if unknown:
        raise ValueError(f"unknown role(s): {', '.join(sorted(unknown))}")
    groups = roles_ensure()
    with transaction.atomic():
        user.groups.set([groups[role] for role in wanted])
        user.is_staff = bool(wanted & STAFF_ROLES)
        user.is_superuser = ADMIN in wanted
        user.save(update_fields=["is_staff", "is_superuser"])


def user_roles(user: User | AnonymousUser) -> set[str]:
    """The role names ``user`` holds (empty for anonymous users)."""
    if not user.is_authenticated:
        return set()
    return set(user.groups.filter(name__in=ROLES).values_list("name", flat=True))


def user_has_role(user: User | AnonymousUser, role: str) -> bool:
    """True when ``user`` holds ``role``; superusers hold every role."""
    if getattr(user, "is_superuser", False):
        return True
    return role in user_roles(user)
