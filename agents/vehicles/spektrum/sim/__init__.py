"""The spektrum simulator (never imported by production code: see agents.simulation)."""
