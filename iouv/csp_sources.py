"""Content-Security-Policy sources that the settings derive from other settings."""

from __future__ import annotations

from urllib.parse import urlsplit

from django.core.exceptions import ImproperlyConfigured


def csp_origin_of_template(url: str, *, setting: str) -> str | None:
    """The CSP host-source allowing every URL that the URL template ``url`` can expand
    to, e.g. ``https://*.tile.example.org`` for
    ``https://{s}.tile.example.org/{z}/{x}/{y}.png`` (Leaflet's tile templates).

    Returns None for an empty or relative URL: those are the platform's own origin,
    which ``'self'`` already allows. A placeholder anywhere in the host but its first
    label has no CSP source form: ImproperlyConfigured, naming ``setting``.
    """
    if not url:
        return None
    parts = urlsplit(url)
    if not parts.netloc:
        return None
    if parts.scheme not in {"http", "https"} or not parts.hostname:
        raise ImproperlyConfigured(f"{setting}={url!r}: give an http(s) URL with a host")
    netloc = parts.netloc.rpartition("@")[2]  # never user:password@ in a policy
    if netloc.startswith("["):  # an IPv6 literal, with no placeholder to widen
        return f"{parts.scheme}://{netloc}"
    host, sep, port = netloc.partition(":")
    if port and not port.isdigit():
        raise ImproperlyConfigured(f"{setting}={url!r}: the port must be a number")
    first, dot, rest = host.partition(".")
    if "{" in rest or "}" in rest:
        raise ImproperlyConfigured(
            f"{setting}={url!r}: only the host's first label may be a placeholder"
        )
    if "{" in first or "}" in first:
        first = "*"  # CSP's wildcard covers exactly one leftmost label, or more
    return f"{parts.scheme}://{first}{dot}{rest}{sep}{port}"
