"""Benchmarks behind ``clgs bench``: each module has a click command ``main`` that prints a table."""
