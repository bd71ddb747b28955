"""geocd: 3-D change detection from satellite (RPC) and aerial (frame) images, DEMs and footprints."""

import os as _os

__version__ = "0.1.0"

# numba's OpenMP worker threads spin while waiting; on a shared or oversubscribed machine that makes small
# parallel kernels 10-100x slower (measured here: 23 ms instead of 0.09 ms per tile slice). Passive waiting
# costs nothing measurable on an idle machine. Only a default: an explicit OMP_WAIT_POLICY wins. Set before
# any numba kernel starts its thread pool (geocd is imported first).
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import os as _os  # noqa: E402

# numba's OpenMP workers sleep instead of spinning between parallel regions: spinning threads make
# parallel kernels 10-30x slower on a loaded machine (measured in bench/bench_stereo.py); set before
# the first parallel kernel runs, overridable by the user's environment.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import GeoCDError  # noqa: E402,F401
