"""The adapter kit: one reader for every adapter's options.

Every integration reads the ``adapter_options`` of its agent config through an
:class:`OptionReader`, so they all mean the same thing by a number, a flag or an origin:

* every read names its key in the error it raises: ``"<integration> option <key>:
  <what is wrong>"`` (a ValueError, which the agent reports as a config error);
* a number is a finite JSON number (never a boolean) inside its range; an integer has
  no fraction; a flag is ``true`` or ``false`` (the string ``"false"`` is no flag, and
  a JSON slip must not switch a safety check off); a choice is one of its words;
* ``origin`` is ``[lat, lon]``: where a simulated vehicle starts, or where a real one
  without GPS counts from;
* :meth:`OptionReader.finish` refuses the keys nobody read, naming them: a misspelt
  ``distance_sensor`` must not leave the obstacle stop silently off.

Keys every adapter accepts without reading them: the agent's own (:data:`AGENT_KEYS`)
and ``simulator``, the simulator's parameters, read by the integration's simulator
hook (:func:`simulator_split` hands them over). ``simulate: true`` is refused with a
word on where simulators start: by ``python -m agents sim fleet``
(:mod:`agents.simulation`), never by an adapter.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

#: Keys of ``adapter_options`` that the agent itself reads (its profile).
AGENT_KEYS = frozenset({"vehicle_type", "attributes"})
#: The key holding the simulator's own parameters (see :func:`simulator_split`).
SIMULATOR_KEY = "simulator"


class OptionReader:
    """Reads one adapter's options, remembering which keys were read.

    ``integration`` names the options in errors; ``prefix`` is put before every key
    (``"simulator."`` for the simulator's parameters). Nothing is read twice on
    purpose: each key has one meaning, checked in one place.
    """

    def __init__(self, integration: str, options: Mapping[str, Any], *, prefix: str = "") -> None:
        self.where = f"{integration} options" + (f" {prefix.rstrip('.')}" if prefix else "")
        if not isinstance(options, Mapping):
            raise ValueError(f"{self.where}: expected an object")
        self.integration = integration
        self.options = options
        self.prefix = prefix
        self.read: set[str] = set()

    # --- errors and raw access -----------------------------------------------------------
    def error(self, key: str, problem: str) -> ValueError:
        """The error for option ``key``: ``"<integration> option <prefix><key>: ..."``."""
        return ValueError(f"{self.integration} option {self.prefix}{key}: {problem}")

    def has(self, key: str) -> bool:
        """Whether ``key`` is given (not null); counts as reading it."""
        self.read.add(key)
        return self.options.get(key) is not None

    def get(self, key: str, default: Any = None) -> Any:
        """The raw value of ``key`` (``default`` when absent or null), for checks of the
        integration's own; counts as reading it."""
        self.read.add(key)
        value = self.options.get(key)
        return default if value is None else value

    # --- typed reads -----------------------------------------------------------------------
    def number(
        self,
        key: str,
        default: float,
        *,
        min: float | None = None,
        above: float | None = None,
        max: float | None = None,
    ) -> float:
        """A finite number; ``min``/``max`` inclusive, ``above`` exclusive."""
        value = self.get(key, default)
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise self.error(key, "expected a number")
        if min is not None and value < min:
            raise self.error(key, f"must be >= {min:g}")
        if above is not None and value <= above:
            raise self.error(key, f"must be > {above:g}")
        if max is not None and value > max:
            raise self.error(key, f"must be <= {max:g}")
        return float(value)

    def integer(
        self,
        key: str,
        default: int,
        *,
        min: int | None = None,
        max: int | None = None,
    ) -> int:
        """An integer within ``min``..``max`` (inclusive)."""
        value = self.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, "expected an integer")
        if (min is not None and value < min) or (max is not None and value > max):
            low = "" if min is None else f"{min}"
            high = "" if max is None else f"{max}"
            raise self.error(key, f"must be within {low}..{high}")
        return value

    def optional_integer(
        self,
        key: str,
        *,
        min: int | None = None,
        max: int | None = None,
    ) -> int | None:
        """An integer like :meth:`integer`, or None when not given."""
        if not self.has(key):
            return None
        return self.integer(key, 0, min=min, max=max)

    def optional_number(
        self,
        key: str,
        *,
        min: float | None = None,
        above: float | None = None,
        max: float | None = None,
    ) -> float | None:
        """A number like :meth:`number`, or None when not given."""
        if not self.has(key):
            return None
        return self.number(key, 0.0, min=min, above=above, max=max)

    def flag(self, key: str, default: bool = False) -> bool:
        """``true`` or ``false``, strictly."""
        value = self.get(key, default)
        if not isinstance(value, bool):
            raise self.error(key, "expected true or false")
        return value

    def choice(self, key: str, default: str, choices: Iterable[str]) -> str:
        """One of ``choices``."""
        allowed = list(choices)
        value = self.get(key, default)
        if value not in allowed:
            raise self.error(key, f"one of {', '.join(allowed)}")
        return str(value)

    def text(self, key: str, default: str, *, what: str = "text") -> str:
        """A non-empty string; ``what`` says what it should be, in the error."""
        value = self.get(key, default)
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected {what}")
        return value

    def mapping(self, key: str) -> dict[str, Any]:
        """A JSON object (``{}`` when absent)."""
        value = self.get(key, {})
        if not isinstance(value, Mapping):
            raise self.error(key, "expected an object")
        return dict(value)

    def names(self, key: str, choices: Sequence[str]) -> list[str]:
        """A list of words, each one of ``choices`` (``[]`` when absent)."""
        value = self.get(key, [])
        if not isinstance(value, Sequence) or isinstance(value, str):
            raise self.error(key, "a list of names")
        for name in value:
            if name not in choices:
                raise self.error(key, f"{name!r} is not one of {', '.join(choices)}")
        return list(value)

    def origin(self, key: str = "origin") -> tuple[float, float] | None:
        """``[lat, lon]`` in degrees, or None when not given."""
        value = self.get(key)
        if value is None:
            return None
        if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
            raise self.error(key, "expected [lat, lon]")
        lat, lon = value
        if any(isinstance(v, bool) or not isinstance(v, int | float) for v in (lat, lon)):
            raise self.error(key, "expected [lat, lon]")
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise self.error(key, "latitude or longitude out of range")
        return (float(lat), float(lon))

    # --- the end ----------------------------------------------------------------------------
    def finish(self, *, accepted: Iterable[str] = ()) -> None:
        """Refuse every key that was not read (besides :data:`AGENT_KEYS`, ``simulator``
        and ``accepted``), naming them all."""
        if not self.prefix and self.options.get("simulate", False) is not False:
            raise self.error(
                "simulate",
                "simulators are started by `python -m agents sim fleet`, never by the "
                "adapter; give the simulator's parameters as `simulator`",
            )
        known = self.read | set(accepted)
        if not self.prefix:
            # simulate: false was how a config said "real hardware"; it is the only way now.
            known |= AGENT_KEYS | {SIMULATOR_KEY, "simulate"}
        unknown = sorted(str(key) for key in self.options if key not in known)
        if unknown:
            keys = "key" if len(unknown) == 1 else "keys"
            raise ValueError(f"{self.where}: unknown {keys} {', '.join(unknown)}")


def simulator_split(options: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(adapter options without "simulator", the simulator's parameters)``: what a
    simulator hook starts from. Raises ValueError when ``simulator`` is not an object."""
    adapter = dict(options)
    simulator = adapter.pop(SIMULATOR_KEY, None) or {}
    if not isinstance(simulator, Mapping):
        raise ValueError("adapter option simulator: expected an object")
    return adapter, dict(simulator)
