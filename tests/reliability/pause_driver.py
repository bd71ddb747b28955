"""Run the geocd CLI, pausing inside the N-th product write (the ``.part`` file complete, not yet renamed).

Used by the signal and concurrency tests to put a real geocd process in the middle of writing:

    python pause_driver.py FLAG GO N geocd-args...

writes FLAG (holding the temporary file's path) when it pauses, and resumes when the file GO exists
(or after 120 s). Nothing else of geocd is changed.
"""

import os
import sys
import time
from pathlib import Path


def main() -> None:
    flag, go, nth = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
    args = sys.argv[4:]
    real_replace = os.replace
    count = {"n": 0}

    def replace(src, dst, *a, **kw):
        if ".part" in os.path.basename(str(src)):
            count["n"] += 1
            if count["n"] == nth:
                flag.write_text(str(src))
                t0 = time.monotonic()
                while not go.exists() and time.monotonic() - t0 < 120:
                    time.sleep(0.05)
        return real_replace(src, dst, *a, **kw)

    os.replace = replace
    from geocd.cli import main as geocd_main

    sys.argv = ["geocd", *args]
    geocd_main(args, prog_name="geocd")


if __name__ == "__main__":
    main()
