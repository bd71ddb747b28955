"""The committed scene's images, one picture per epoch (docs/getting-started.md): a satellite view, and an aerial
frame where the epoch has one, each with its sun.

Usage::

    .venv/bin/python bench/figures/sample_aoi_epochs.py [--out docs]     # → OUT/sample_aoi_epoch_{A,B}.png

(:func:`geocd.synth.pictures.write_pictures`, which ``geocd synth --pictures DIR`` calls for a generated scene;
its truth pictures, ``sample_aoi_dsm.png`` and ``sample_aoi_change.png``, are not kept: the docs show what the
run finds, not the truth mask.)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from shutil import copyfile

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from geocd.synth.pictures import write_pictures  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default=str(REPO / "sample_aoi"))
    ap.add_argument("--out", default=str(REPO / "docs"))
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        written = write_pictures(a.scene, tmp, prefix="sample_aoi_")
        for key, path in written.items():
            if key.startswith("epoch_"):
                dst = Path(a.out) / Path(path).name
                copyfile(path, dst)
                print(dst)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
