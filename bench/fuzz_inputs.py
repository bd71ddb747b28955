"""Long fuzzing runs of geocd's readers: every mutated input gives a result or a GeoCDError, nothing else.

The same targets as tests/reliability/test_fuzz.py and test_fuzz_models.py (CI runs a few hundred examples of
each: manifests, DEM GeoTIFFs, RPC tags, self-consistency models, frame sidecars, PyTorch weights) and the RPC file
mutations of tests/io/test_rpc_readers.py, here for thousands of examples each (hypothesis, generate phase only,
no example database). Prints per target: examples run, outcomes (accepted / each GeoCDError class) and the
exceptions outside GeoCDError (must be 0; the first few are shown).

Usage::

    nice .venv/bin/python bench/fuzz_inputs.py [--examples 10000] [--targets manifest_tree,rpc_tags,...]
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from hypothesis import HealthCheck, Phase, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from geocd.errors import GeoCDError  # noqa: E402
from tests.reliability import fuzz_targets as F  # noqa: E402
from tests.reliability.scenes import make_scene, write_dem_pair  # noqa: E402


def run_target(name: str, strategy, check, n: int) -> dict:
    tally: collections.Counter = collections.Counter()
    bad: list[str] = []

    @settings(
        max_examples=n, phases=[Phase.generate], database=None, deadline=None, suppress_health_check=list(HealthCheck)
    )
    @given(x=strategy)
    def go(x):
        try:
            tally[check(x)] += 1
        except GeoCDError as exc:  # a target that lets a GeoCDError through counts it too
            tally[type(exc).__name__] += 1
        except Exception as exc:  # noqa: BLE001 - what we are looking for
            tally["OUTSIDE GeoCDError"] += 1
            if len(bad) < 5:
                bad.append(f"{type(exc).__name__}: {exc} <- {x!r:.300}\n{traceback.format_exc(limit=3)}")

    t0 = time.perf_counter()
    go()
    return {
        "name": name,
        "examples": sum(tally.values()),
        "tally": tally,
        "bad": bad,
        "seconds": time.perf_counter() - t0,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=10_000)
    ap.add_argument(
        "--targets",
        default="manifest_tree,manifest_text,dem_bytes,rpc_tags,rpc_files,model_tree,"
        "model_bytes,frame_sidecar,torch_bytes",
    )
    args = ap.parse_args()
    wanted = args.targets.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="geocd_fuzz_"))
    scene = make_scene(tmp / "scene")
    doc = yaml.safe_load(scene.manifest.read_text())
    mt = tmp / "mt"
    mt.mkdir()
    (mt / "images").symlink_to(scene.root / "images")
    for f in ("dem.tif", "footprints.gpkg"):
        (mt / f).symlink_to(scene.root / f)
    dem, _ = write_dem_pair(tmp / "dem", rows=24, cols=24)
    dem_bytes = dem.read_bytes()
    (tmp / "dm").mkdir()
    from geocd.io.raster import write_image
    from tests.stereo.synthetic import affine_rpc

    img = write_image(tmp / "img.tif", np.ones((1, 16, 16), np.uint8))
    tags = F.rpc_tags_of(affine_rpc(0.5, (0.5, 0.05), 120, 120))

    import json

    from tests.camera.test_frame import make_cam
    from tests.screen.test_torchfile import _tensor_pickle, _zip

    from geocd.io.frame import write_frame_sidecar

    model_doc = json.loads((REPO / "examples/kahramanmaras/marseille_urban_model.json").read_text())
    (tmp / "mo").mkdir()
    sidecar = json.loads(Path(write_frame_sidecar(tmp / "frame.json", make_cam())).read_text())
    torch_bytes = _zip(tmp / "w.pth", _tensor_pickle(0, (2, 2), (2, 1))).read_bytes()
    targets = {
        "model_tree": (F.tree_ops, lambda ops: F.check_model_tree(model_doc, ops, tmp / "mo")),
        "model_bytes": (F.byte_mutations, lambda m: F.check_model_bytes(json.dumps(model_doc).encode(), m, tmp / "mo")),
        "frame_sidecar": (F.tree_ops, lambda ops: F.check_frame_sidecar(sidecar, ops, tmp / "mo")),
        "torch_bytes": (F.byte_mutations, lambda m: F.check_torch_bytes(torch_bytes, m, tmp / "mo")),
        "manifest_tree": (F.tree_ops, lambda ops: F.check_manifest_tree(doc, ops, scene.root)),
        "manifest_text": (F.byte_mutations, lambda m: F.check_manifest_text(F.dump_yaml(doc), m, mt)),
        "dem_bytes": (F.byte_mutations, lambda m: F.check_dem_bytes(dem_bytes, m, tmp / "dm")),
        "rpc_tags": (F.rpc_tag_edits, lambda e: F.check_rpc_tags(img, tags, e)),
    }
    if "rpc_files" in wanted:
        from geocd.io.rpc import read_rpc
        from tests.io import test_rpc_readers as R

        model = R.synthetic_rpc(seed=7)
        rd = tmp / "rpcfmt"
        rd.mkdir()
        written = {name: w(model, rd / name) for name, w in R.WRITERS.items()}
        md = tmp / "rpcmut"
        md.mkdir()

        def rpc_file(x):
            name, mutation = x
            src = written[name]
            p = md / src.name
            p.write_bytes(
                R._mutate(
                    src.read_bytes(),
                    mutation[0],
                    mutation[1],
                    mutation[2],
                    mutation[3],
                    np.random.default_rng(mutation[4]),
                )
            )
            try:
                m = read_rpc(p)
            except GeoCDError as exc:
                return type(exc).__name__
            c, r = m.project(m.lon_off, m.lat_off, m.height_off)
            assert np.isfinite(c) and np.isfinite(r), "accepted model projects to a non-finite pixel"
            return "ok"

        targets["rpc_files"] = (st.tuples(st.sampled_from(sorted(written)), R._mutations), rpc_file)

    total_ex = total_bad = 0
    print(f"{'target':<15} {'examples':>8} {'outside':>8} {'s':>7}  outcomes")
    for name in wanted:
        strat, check = targets[name]
        res = run_target(name, strat, check, args.examples)
        outside = res["tally"].get("OUTSIDE GeoCDError", 0)
        total_ex += res["examples"]
        total_bad += outside
        tops = ", ".join(f"{k} {v}" for k, v in res["tally"].most_common(5))
        print(f"{name:<15} {res['examples']:>8} {outside:>8} {res['seconds']:>7.1f}  {tops}", flush=True)
        for b in res["bad"]:
            print("   ", b.replace("\n", "\n    "))
    print(f"total: {total_ex} examples, {total_bad} exceptions outside GeoCDError")
    return 1 if total_bad else 0


if __name__ == "__main__":
    sys.exit(main())
