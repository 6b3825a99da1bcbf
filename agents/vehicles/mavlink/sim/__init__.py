"""The mavlink simulator (never imported by production code: see agents.simulation)."""
