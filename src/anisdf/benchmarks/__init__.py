"""Library-side benchmark code, shipped with the package: ``anisdf bench`` (:mod:`.speed`) calls down into it.

:mod:`.encoding` (hash-grid speed), :mod:`.normals` (analytic vs finite-difference normals), :mod:`.opcount`
(operators per training step) and :mod:`.speed` (training-step throughput, memory, time to quality). They sit
above :mod:`anisdf.training` and :mod:`anisdf.tasks` and may import them; nothing in the library imports them. The
repository's top-level
``benchmarks/`` folder holds only runnable scripts that call these modules, and ``RESULTS.md`` with the figures.
"""
