"""The scripts that draw the pictures README.md and docs/ show, and the one command that runs them all.

``python -m bench.figures --list`` lists them (:mod:`bench.figures.registry`); ``python -m bench.figures`` makes
them from fresh runs and stamps each with its command, data and date (:mod:`bench.figures.stamp`).
"""
