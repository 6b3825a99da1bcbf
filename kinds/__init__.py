"""Service kinds: one folder (a Django app) per kind of service, each registering its
``services.kinds.ServiceKind`` when the app is ready. See docs/writing-a-service.md."""
