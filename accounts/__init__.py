"""Users, roles (client, monitor, operator, admin) and login."""
