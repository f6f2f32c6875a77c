"""Benchmarks of the sensor, the base station and the map; each module runs as ``python -m benchmarks.NAME``.

Not part of the installed package: they are run from a checkout, whose root must be on the import path (the
current directory with ``python -m``, or pytest's ``pythonpath`` setting for the tests that import them).
"""
