"""Flight records: the batches vehicles upload, kept with their sessions (``keeping``),
and their exports (``exports``: GPX, KML, CSV, tlog)."""
