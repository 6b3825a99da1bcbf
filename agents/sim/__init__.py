"""Simulators that stand in for vehicle hardware in tests and demos."""
