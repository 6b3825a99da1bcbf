"""Stations, vehicle types, declared attributes, vehicles, credentials and live status."""
