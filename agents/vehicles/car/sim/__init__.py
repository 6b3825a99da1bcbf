"""The car simulator (never imported by production code: see agents.simulation)."""
