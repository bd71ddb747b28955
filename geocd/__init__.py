"""geocd: 3-D change detection from satellite (RPC) and aerial (frame) images, DEMs and footprints."""

__version__ = "0.1.0"

import os as _os  # noqa: E402

# numba's OpenMP workers sleep instead of spinning between parallel regions: spinning threads make
# parallel kernels 10-30x slower on a loaded machine (measured in bench/bench_stereo.py); set before
# the first parallel kernel runs, overridable by the user's environment.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .errors import GeoCDError  # noqa: E402,F401
