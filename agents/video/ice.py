"""ICE for the agent's WebRTC connections: which local addresses aioice offers as host
candidates, and ICE servers from the agent's configuration.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

from aiortc import RTCIceServer

from agents.video import VideoError

# --------------------------------------------------------------------------------------
# ICE host candidates
# --------------------------------------------------------------------------------------

# aioice offers every address of every interface except 127.0.0.1, and has no per-
# connection option to choose them. We wrap its module-level get_host_addresses once so
# that it honours this context variable; unset (the default) it behaves exactly as
# before, so other aiortc users in the process are unaffected. aiortc gathers inside
# setLocalDescription, in tasks that inherit the caller's context, so setting the
# variable around that call scopes the restriction to one peer connection.
_ICE_HOST_ADDRESSES: contextvars.ContextVar[tuple[str, ...] | None] = contextvars.ContextVar(
    "iouv_ice_host_addresses", default=None
)


def _install_ice_host_hook() -> None:
    import aioice.ice

    original = aioice.ice.get_host_addresses
    if getattr(original, "_iouv_hook", False):
        return

    def get_host_addresses(use_ipv4: bool, use_ipv6: bool) -> list[str]:
        only = _ICE_HOST_ADDRESSES.get()
        if only is None:
            return original(use_ipv4, use_ipv6)
        return [a for a in only if (use_ipv6 if ":" in a else use_ipv4)]

    get_host_addresses._iouv_hook = True  # type: ignore[attr-defined]
    aioice.ice.get_host_addresses = get_host_addresses


@contextlib.contextmanager
def restrict_ice_host_addresses(addresses: Sequence[str] | None) -> Iterator[None]:
    """Within the block (and tasks started from it), aioice offers only ``addresses`` as
    host candidates; None leaves aioice's choice. For loopback-only setups
    (``["127.0.0.1"]``), which aioice otherwise never offers."""
    if addresses is None:
        yield
        return
    _install_ice_host_hook()
    token = _ICE_HOST_ADDRESSES.set(tuple(addresses))
    try:
        yield
    finally:
        _ICE_HOST_ADDRESSES.reset(token)


def ice_server(spec: RTCIceServer | Mapping[str, Any] | str) -> RTCIceServer:
    """An ``RTCIceServer`` from its configuration: an object, ``{"urls", "username",
    "credential"}`` or a URL. Raises VideoError naming what is wrong."""
    if isinstance(spec, RTCIceServer):
        return spec
    if isinstance(spec, str):
        return RTCIceServer(urls=spec)
    if not isinstance(spec, Mapping) or "urls" not in spec:
        raise VideoError("an ICE server needs 'urls'")
    return RTCIceServer(
        urls=spec["urls"], username=spec.get("username"), credential=spec.get("credential")
    )
