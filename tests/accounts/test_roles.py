"""Roles as groups with permissions; login and logout."""

from __future__ import annotations

import pytest
from django.contrib.auth.models import AnonymousUser

from accounts.roles import (
    ADMIN,
    CLIENT,
    MONITOR,
    OPERATOR,
    user_roles,
    user_set_roles,
)
from services.sessions.grants import services_for_user, services_usable
from tests import factories as f

pytestmark = pytest.mark.django_db


def test_each_role_carries_its_permissions():
    client, monitor, operator, admin = (
        f.user(roles=(CLIENT,)),
        f.user(roles=(MONITOR,)),
        f.user(roles=(OPERATOR,)),
        f.user(roles=(ADMIN,)),
    )
    assert client.has_perm("services.use_services") and not client.has_perm("fleet.view_fleet")
    assert not client.is_staff
    assert monitor.has_perm("services.stop_session") and monitor.has_perm("fleet.view_fleet")
    assert not monitor.has_perm("fleet.set_maintenance")
    assert operator.has_perm("fleet.set_maintenance")
    assert not operator.has_perm("services.stop_session")
    assert admin.is_superuser and admin.has_perm("services.stop_session")


def test_a_user_can_hold_several_roles():
    u = f.user(roles=(CLIENT, MONITOR))
    assert user_roles(u) == {CLIENT, MONITOR}
    assert u.is_staff and MONITOR in user_roles(u) and OPERATOR not in user_roles(u)
    user_set_roles(user=u, roles=[CLIENT])
    u.refresh_from_db()
    assert user_roles(u) == {CLIENT} and not u.is_staff


def test_unknown_role_is_refused():
    with pytest.raises(ValueError, match="pilot"):
        user_set_roles(user=f.user(), roles=["pilot"])


def test_grants_by_group_and_by_user():
    public = f.service("public")
    private = f.service("private", grant_clients=False)
    alice, bob = f.user("alice"), f.user("bob")
    private.grants.create(user=bob)
    assert list(services_for_user(alice)) == [public]
    assert set(services_for_user(bob)) == {public, private}
    # A grant alone is not enough: the user must hold the client role's permission.
    private.grants.create(user=f.user("mallory", roles=(OPERATOR,)))
    assert not services_for_user(private.grants.get(user__username="mallory").user).exists()


def test_a_service_read_with_the_users_right_to_it_agrees_with_the_catalog():
    public = f.service("public")
    private = f.service("private", grant_clients=False)
    off = f.service("off", is_active=False)
    bob, mallory = f.user("bob"), f.user("mallory", roles=(OPERATOR,))
    private.grants.create(user=bob)
    private.grants.create(user=mallory)
    people = [f.user("alice"), bob, mallory, f.user("root", roles=(ADMIN,)), AnonymousUser()]
    for user in people:
        usable = {s.slug: s.usable for s in services_usable(user)}
        assert set(usable) == {public.slug, private.slug}  # active ones, usable or not
        assert {slug for slug, yes in usable.items() if yes} == {
            s.slug for s in services_for_user(user)
        }, user
    assert off.slug not in {s.slug for s in services_usable(people[3])}


def test_login_shows_the_granted_catalog_and_logout(client):
    f.service("drive-car")
    f.service("hidden", grant_clients=False)
    f.user("carla")
    assert client.get("/").status_code == 302  # login required
    response = client.post("/accounts/login/", {"username": "carla", "password": "pw-for-tests"})
    assert response.status_code == 302
    page = client.get("/").content.decode()
    assert 'data-service="drive-car"' in page and 'data-service="hidden"' not in page
    client.post("/accounts/logout/")
    assert client.get("/").status_code == 302


def test_wrong_password_is_refused(client):
    f.user("carla")
    response = client.post("/accounts/login/", {"username": "carla", "password": "nope"})
    assert response.status_code == 200
    assert "didn't match" in response.content.decode()


@pytest.mark.parametrize(
    "role, says, links",
    [
        (MONITOR, "you are monitor", ["/monitor/"]),
        (OPERATOR, "you are operator", ["/admin/"]),
        (None, "Ask an administrator to grant you the client role", []),
    ],
)
def test_an_empty_catalog_says_why_and_where_to_go(client, role, says, links):
    f.service("drive-car")
    user = f.user("someone", roles=(role,) if role else ())
    client.force_login(user)
    page = client.get("/").content.decode()
    assert "data-empty-catalog" in page and "No service is open to you." in page
    assert says in page
    for link in links:
        assert f'href="{link}"' in page


def test_a_page_that_is_not_there_or_not_yours_answers_in_the_portals_words(client, settings):
    settings.DEBUG = False
    client.force_login(f.user("carla"))
    answer = client.get("/spectate/")  # spectating is not granted to carla
    assert answer.status_code == 404
    page = answer.content.decode()
    assert "data-not-found" in page and "not open to your account (carla)" in page
    assert 'href="/"' in page
