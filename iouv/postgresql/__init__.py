"""Django's PostgreSQL backend, its pool checking connections as iouv.db_pool does."""
