"""Authentication backend: Django's own, with a user's permissions read in one query.

Every API call that checks a permission asks ``user.has_perm``. Django's
ModelBackend reads the user's own permissions and their groups' (roles') in two
queries; :class:`RoleBackend` reads both in one. Everything else (passwords, inactive
users, superusers, the per-user cache) is ModelBackend's, unchanged.

Enabled by ``AUTHENTICATION_BACKENDS = ["accounts.backends.RoleBackend"]``.
"""

from __future__ import annotations

from typing import Any

from django.contrib.auth.backends import ModelBackend
from django.contrib.auth.models import AnonymousUser, Group, Permission
from django.db.models import Q, QuerySet

from accounts.users import User
from iouv.prepared import Param, PreparedQuery


def _permissions_of(user: User | Param) -> QuerySet[Permission, tuple[str, str]]:
    """``user``'s permissions as (app_label, codename): every one for a superuser, else
    their own and their groups'. Two subqueries rather than joins both ways, which
    would multiply a permission's rows by the users of every group holding it."""
    if isinstance(user, User) and user.is_superuser:
        perms = Permission.objects.all()
    else:
        pk = user if isinstance(user, Param) else user.pk
        own = User.user_permissions.through.objects.filter(user_id=pk)
        groups = User.groups.through.objects.filter(user_id=pk).values("group_id")
        grouped = Group.permissions.through.objects.filter(group_id__in=groups)
        perms = Permission.objects.filter(
            Q(pk__in=own.values("permission_id")) | Q(pk__in=grouped.values("permission_id"))
        )
    return perms.values_list("content_type__app_label", "codename").order_by()


# What every API request that checks a permission reads: composed once (iouv.prepared).
_PERMISSIONS: PreparedQuery[Any] = PreparedQuery(
    lambda: _permissions_of(Param("user", User._meta.pk))
)


class RoleBackend(ModelBackend):
    """ModelBackend whose ``get_all_permissions`` (what ``has_perm`` asks) is one query.

    Same answers as ModelBackend: an empty set for an inactive or anonymous user and
    for object permissions; every permission for an active superuser; cached on the
    user object (``_perm_cache``) for the rest of the request.
    """

    def get_all_permissions(self, user_obj: User | AnonymousUser, obj: Any = None) -> set[str]:
        if not user_obj.is_active or user_obj.is_anonymous or obj is not None:
            return set()
        if not hasattr(user_obj, "_perm_cache"):
            rows = (
                _permissions_of(user_obj)
                if user_obj.is_superuser
                else _PERMISSIONS.all(user=user_obj.pk)
            )
            perms = {f"{label}.{codename}" for label, codename in rows}
            user_obj._perm_cache = perms  # type: ignore[attr-defined]
        return user_obj._perm_cache  # type: ignore[attr-defined,no-any-return]

    async def aget_all_permissions(
        self, user_obj: User | AnonymousUser, obj: Any = None
    ) -> set[str]:
        if not user_obj.is_active or user_obj.is_anonymous or obj is not None:
            return set()
        if not hasattr(user_obj, "_perm_cache"):
            rows = _permissions_of(user_obj)
            perms = {f"{label}.{codename}" async for label, codename in rows}
            user_obj._perm_cache = perms  # type: ignore[attr-defined]
        return user_obj._perm_cache  # type: ignore[attr-defined,no-any-return]
