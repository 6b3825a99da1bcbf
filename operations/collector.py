"""The garbage collector of a platform process: full collections rare and short.

A full collection (generation 2) stops the whole process, the event loop carrying every
uplink and relayed command and the request threads alike, for as long as it takes to
walk every object the collector tracks. With 1,000 agents connected that was 150-220 ms,
every 7 s or so under 24 sessions/s of API load (the scale benchmark, logging each
collection): most of the requests slower than 100 ms were waiting behind one.

Two causes, two settings:

* Python collects its youngest generation every 700 allocations net. A request makes
  tens of thousands, so every object it holds is swept through the young generations
  while the request is still using it, and lands in the oldest. Those objects die soon
  after, but only a full collection looks there again: the oldest generation grows by a
  quarter, and Python runs a full collection. Collecting the youngest generation every
  ``IOUV_GC_YOUNG_THRESHOLD`` allocations instead lets a request's objects die young
  (freed by reference counting, or in a young collection) instead of filling the oldest.
* About 140,000 objects exist once the platform is imported (modules, classes,
  functions, Django's and the API's schemas) and live as long as the process. A full
  collection walked them every time, about 45 ms of each. ``gc.freeze()`` at start-up
  moves them out of the collector's sight.
"""

from __future__ import annotations

import gc


def collector_tune(young_threshold: int) -> None:
    """Freeze what exists now and collect the youngest generation every
    ``young_threshold`` net allocations (0: leave Python's thresholds). Called once, when
    the application has been imported."""
    gc.collect()
    # What is left now lives as long as the process: never walked again.
    gc.freeze()
    if young_threshold > 0:
        _, middle, oldest = gc.get_threshold()
        gc.set_threshold(young_threshold, middle, oldest)
