"""Vehicle integrations, one folder each (adapter, options, wire format, simulator), behind
the adapter interface of :mod:`agents.vehicles.base`; :mod:`agents.vehicles.registry`
finds them by name."""
