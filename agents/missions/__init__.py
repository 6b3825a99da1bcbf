"""Autonomous missions, one folder each (typed spec, runner, tests, docs), flown on the
shared flight kit of :mod:`agents.missions.kit`; :mod:`agents.missions.registry` finds
them, and the vehicle task's ``mission`` is the tagged union of their specs.

This package and each mission's ``__init__`` and ``spec`` stay light (msgspec only): the
platform imports the specs through :mod:`agents.protocol` to build and sign missions,
and must not load a runner, numpy or a camera library to do so.
"""
