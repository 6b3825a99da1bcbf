from django.apps import AppConfig
from django.db.models.signals import post_migrate


class AccountsConfig(AppConfig):
    name = "accounts"
    verbose_name = "Accounts and roles"

    def ready(self) -> None:
        from accounts.roles import roles_ensure_on_migrate

        # Permissions are created by post_migrate too, so the role groups are
        # (re)filled after every migrate; the handler is idempotent.
        post_migrate.connect(roles_ensure_on_migrate, dispatch_uid="accounts.roles_ensure")
