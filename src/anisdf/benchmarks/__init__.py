"""Benchmarks shipped with the package (``anisdf bench``)."""
