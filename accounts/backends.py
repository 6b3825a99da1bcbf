"""Authentication backend: Django's own, with a user's permissions read in one query.

Every API call that checks a permission asks ``user.has_perm``. Django's
ModelBackend reads the user's own permissions and their groups' (roles') in two
queries; :class:`RoleBackend` reads both in one. Everything else (passwords, inactive
users, superusers, the per-user cache) is ModelBackend's, unchanged.

Enabled by ``AUTHENTICATION_BACKENDS = ["accounts.backends.RoleBackend"]``.

An API call reads its token with its user anyway (accounts.tokens): the same statement
brings the user's permissions along (:func:`permissions_joined`), so that a call that
checks one costs no query of its own.
"""

from __future__ import annotations

from typing import Any

from django.contrib.auth.backends import ModelBackend
from django.contrib.auth.models import AnonymousUser, Group, Permission
from django.db.models import Func, OuterRef, Q, QuerySet, Subquery, TextField, Value
from django.db.models.functions import Concat

from accounts.users import User


def _permission_rows(user: User | OuterRef) -> QuerySet[Permission]:
    """``user``'s permissions: every one for a superuser, else their own and their
    groups'. Two subqueries rather than joins both ways, which would multiply a
    permission's rows by the users of every group holding it."""
    if isinstance(user, User) and user.is_superuser:
        return Permission.objects.all()
    pk = user.pk if isinstance(user, User) else user
    own_pk, groups_pk = pk, pk
    if isinstance(user, OuterRef):
        # Seen from the subqueries below, the outer query is one and two levels further.
        own_pk, groups_pk = OuterRef(user), OuterRef(OuterRef(user))
    own = User.user_permissions.through.objects.filter(user_id=own_pk)
    groups = User.groups.through.objects.filter(user_id=groups_pk).values("group_id")
    grouped = Group.permissions.through.objects.filter(group_id__in=groups)
    return Permission.objects.filter(
        Q(pk__in=own.values("permission_id")) | Q(pk__in=grouped.values("permission_id"))
    )


def _permissions_of(user: User) -> QuerySet[Permission, tuple[str, str]]:
    """``user``'s permissions as (app_label, codename)."""
    rows = _permission_rows(user)
    return rows.values_list("content_type__app_label", "codename").order_by()


class _Joined(Func):
    """A one-column subquery's values as one text, separated by commas: an aggregate
    over the whole subquery, which therefore adds no GROUP BY (PostgreSQL's
    ``string_agg``, SQLite's ``group_concat``)."""

    function = "STRING_AGG"
    template = "%(function)s(%(expressions)s, ',')"
    output_field = TextField()

    def as_sqlite(self, compiler: Any, connection: Any, **extra: Any) -> Any:
        return super().as_sql(compiler, connection, function="GROUP_CONCAT", **extra)


def permissions_joined(user: OuterRef) -> Subquery:
    """The permissions of the user ``user`` refers to (an outer query's user id), as
    one text for :func:`permissions_cache`: not for superusers, who hold every one."""
    name = Concat("content_type__app_label", Value("."), "codename", output_field=TextField())
    rows = _permission_rows(user).order_by().values(joined=_Joined(name))
    return Subquery(rows, output_field=TextField())


def permissions_cache(user: User, joined: str | None) -> None:
    """Keep ``joined`` (:func:`permissions_joined`, read with ``user``) as ``user``'s
    permissions for the rest of the request, as :class:`RoleBackend` would have read
    them. Nothing for a superuser, whose permissions are all of them."""
    if user.is_active and not user.is_superuser:
        user._perm_cache = set(joined.split(",")) if joined else set()  # type: ignore[attr-defined]


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
            rows = _permissions_of(user_obj)
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
