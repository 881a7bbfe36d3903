"""The research lab: the trust harness and the diagnosis tools of issue 30 (see README.md).

Not part of the product: nothing in ``ptpcore``, ``app``, ``benchmarks`` or ``tests`` imports it, it is
not installed, and its own tests (``research/tests``) run only when asked (``python -m pytest
research/tests``). The tools run from a checkout: ``python -m research.TOOL ...``.
"""
