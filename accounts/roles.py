"""Roles are Django groups carrying permissions; a user may hold several.

* client   - uses the services their grants allow
* monitor  - watches the fleet and every session, can stop a session
* operator - station staff: puts vehicles in and out of service, and watches the fleet
              and its sessions on the fleet monitor (without stopping them)
* admin    - everything

Permissions are named by string ("app_label.codename") so this module does not import
the apps that define them (accounts sits below fleet and services).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from django.apps import AppConfig, apps
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
        # The fleet monitor shows every session with the vehicles: an operator taking a
        # vehicle out of service must see what it is doing.
        "services.view_session",
    ),
    ADMIN: (),  # every permission, filled in by roles_ensure
}
# Roles whose holders work in the Django admin.
STAFF_ROLES = {MONITOR, OPERATOR, ADMIN}


def _permissions(names: Iterable[str]) -> list[Permission]:
    """The permissions ``names`` ("app_label.codename") name, in one query; those of an
    app that has not migrated yet are absent."""
    wanted = {tuple(name.split(".", 1)) for name in names}
    if not wanted:
        return []
    candidates = Permission.objects.filter(
        codename__in={codename for _, codename in wanted}
    ).select_related("content_type")
    return [p for p in candidates if (p.content_type.app_label, p.codename) in wanted]


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


def roles_ensure_on_migrate(sender: AppConfig, **kwargs: Any) -> None:
    """post_migrate receiver: keep the role groups in step with the permissions.

    Django sends post_migrate once per installed app with models, after each app's
    permissions are made; the groups need every app's, so they are filled once, for
    the last app. (Once per app made every ``flush`` - a transactional test's
    teardown - about 0.4 s slower.)"""
    with_models = [config for config in apps.get_app_configs() if config.models_module]
    if with_models and sender is not with_models[-1]:
        return
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
