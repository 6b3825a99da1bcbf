"""The authentication backend: Django's answers about permissions, in one query."""

from __future__ import annotations

import pytest
from asgiref.sync import async_to_sync
from django.contrib.auth.backends import ModelBackend
from django.contrib.auth.models import AnonymousUser, Permission
from django.db import connection
from django.test.utils import CaptureQueriesContext

from accounts.backends import RoleBackend
from accounts.roles import ADMIN, CLIENT, MONITOR
from accounts.users import User
from tests import factories as f

pytestmark = pytest.mark.django_db


def _fresh(user: User) -> User:
    """The user as a new request reads it: no permissions cached yet."""
    return User.objects.get(pk=user.pk)


@pytest.fixture
def users() -> list[User]:
    """Users holding permissions every way there is, and none."""
    client = f.user(roles=(CLIENT,))
    both = f.user(roles=(CLIENT, MONITOR))
    direct = f.user(roles=())
    direct.user_permissions.add(Permission.objects.get(codename="set_maintenance"))
    mixed = f.user(roles=(CLIENT,))
    mixed.user_permissions.add(Permission.objects.get(codename="use_services"))  # also a role's
    mixed.user_permissions.add(Permission.objects.get(codename="stop_session"))
    inactive = f.user(roles=(MONITOR,))
    inactive.is_active = False
    inactive.save()
    return [client, both, direct, mixed, inactive, f.user(roles=(ADMIN,)), f.user(roles=())]


def test_a_user_has_the_permissions_django_gives(users):
    for user in users:
        expected = ModelBackend().get_all_permissions(_fresh(user))
        assert RoleBackend().get_all_permissions(_fresh(user)) == expected, user.username
        assert async_to_sync(RoleBackend().aget_all_permissions)(_fresh(user)) == expected


def test_the_permissions_are_read_in_one_query_once_per_request(users):
    client = _fresh(users[1])
    with CaptureQueriesContext(connection) as queries:
        RoleBackend().get_all_permissions(client)
        assert RoleBackend().has_perm(client, "services.stop_session")
        assert not RoleBackend().has_perm(client, "fleet.set_maintenance")
    assert len(queries) == 1


def test_inactive_anonymous_and_object_permissions_are_none(users):
    inactive = _fresh(users[4])
    assert RoleBackend().get_all_permissions(inactive) == set()
    assert not RoleBackend().has_perm(inactive, "services.view_session")
    assert RoleBackend().get_all_permissions(AnonymousUser()) == set()
    assert RoleBackend().get_all_permissions(_fresh(users[0]), obj=users[0]) == set()


def test_a_superuser_has_every_permission(users):
    admin = _fresh(users[5])
    assert admin.is_superuser
    assert len(RoleBackend().get_all_permissions(admin)) == Permission.objects.count()


def test_user_has_perm_goes_through_the_backend(users, settings):
    settings.AUTHENTICATION_BACKENDS = ["accounts.backends.RoleBackend"]
    direct = _fresh(users[2])
    with CaptureQueriesContext(connection) as queries:
        assert direct.has_perm("fleet.set_maintenance")
        assert not direct.has_perm("services.use_services")
    assert len(queries) == 1
