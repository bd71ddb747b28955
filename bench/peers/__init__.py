"""geocd against its peers (CARS, xDEM, GDAL), side by side in one run: ``python -m bench.peers``.

:mod:`.rows` the table's rows and goals, :mod:`.install` the peers' own venvs, :mod:`.measure` the runs (calls into
``bench/bench_stereo.py``, ``bench/bench_demdiff.py``, ``bench/bench_rpc.py``), :mod:`.report` the JSON, the
console table and the README's block.
"""
