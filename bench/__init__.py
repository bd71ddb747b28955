"""Benchmarks, evaluations and the figure scripts of the docs (not part of the installed package)."""
