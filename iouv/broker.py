"""kombu's filesystem transport with atomic writes (the embedded mode's Celery broker).

The stock transport creates a message file and then writes it; a consumer polling the
folder can take the file in between, read nothing and die on the empty JSON
(``JSONDecodeError``, an "unrecoverable error" that stops the worker). Here each
message is written under a name the consumer ignores and renamed into place, which
the filesystem does atomically.
"""

from __future__ import annotations

import os
import uuid
from time import monotonic
from typing import Any

from kombu.exceptions import ChannelError
from kombu.transport import filesystem
from kombu.utils.encoding import str_to_bytes
from kombu.utils.json import dumps


class Channel(filesystem.Channel):
    # kombu's filesystem Channel._put has this signature; its stubs ignore the same
    # mismatch with the abstract channel's.
    def _put(self, queue: str, payload: Any, **kwargs: Any) -> None:  # type: ignore[override]
        name = f"{round(monotonic() * 1000)}_{uuid.uuid4()}.{queue}.msg"
        final = os.path.join(self.data_folder_out, name)
        # Not "<queue>.msg" after the first dot: no consumer picks it up half-written.
        partial = os.path.join(self.data_folder_out, f".{name}.partial")
        try:
            with open(partial, "wb") as f:
                f.write(str_to_bytes(dumps(payload)))
            os.replace(partial, final)
        except OSError as exc:
            raise ChannelError(f"Cannot add file {final!r} to directory") from exc


class Transport(filesystem.Transport):
    Channel = Channel
