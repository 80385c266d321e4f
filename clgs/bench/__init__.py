"""Benchmarks behind ``clgs bench``: each module has a click command ``main`` that prints a table.

May import every library layer (it times them); only :mod:`clgs.cli` imports it.
"""
