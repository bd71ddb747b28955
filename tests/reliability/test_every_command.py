"""Every input of every command, given a bad file: one clean error naming that file, exit 2, nothing written.

For each command and each of its file inputs (arguments and options, read from the commands themselves where
they can be), five kinds of bad file: one that does not exist, an empty file, binary garbage, a folder where a
file is expected, and a FIFO (which must be refused, not opened: opening one blocks for ever). The other inputs of
the command are valid, so the error must come from the bad one. A case that runs past its time limit is a hang.

``OUTCOMES`` counts what each case gave (clean error / exit 0 / internal error / traceback / hang) for
docs/reliability.md: ``python -m pytest tests/reliability/test_every_command.py -q -rA``.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from types import SimpleNamespace

import pytest
from click.testing import CliRunner

from geocd.cli import main

from .scenes import REPO, error_lines, make_scene, part_files, sha256_tree, write_dem_pair, write_footprints

#: the seconds a bad-input case may take before it counts as a hang (everything is checked before work)
HANG_S = 60

KINDS = ("missing", "empty", "garbage", "folder", "fifo")


@pytest.fixture(scope="module")
def fx(tmp_path_factory):
    import geopandas as gpd
    import numpy as np

    from geocd.stereo import write_pair_dem
    from tests.change.test_tiled import SHAPE, _pair

    root = tmp_path_factory.mktemp("every_in")
    a, b = write_dem_pair(root / "dems")
    fp = write_footprints(root / "dems" / "footprints.gpkg", a)
    labels = gpd.read_file(fp).assign(**{"class": ["building", "ground"]})
    labels.to_file(root / "dems" / "labels.gpkg")
    rng = np.random.default_rng(0)
    truth = np.zeros(SHAPE, np.float32)
    pa = write_pair_dem(root / "pairs" / "A0.tif", _pair(truth, rng, "A0", "A"))
    pb = write_pair_dem(root / "pairs" / "B0.tif", _pair(truth, rng, "B0", "B"))
    return SimpleNamespace(
        root=root, a=a, b=b, fp=fp, labels=root / "dems" / "labels.gpkg", pa=pa, pb=pb, scene=make_scene(root / "scene")
    )


# command → (base arguments with "{X}" where the bad file goes, the slot's name); {O} is a fresh output path.
# Every file input of every command (checked by test_every_file_input_is_listed).
SLOTS: dict[str, tuple[list[str], str]] = {
    "info PATH": (["info", "{X}"], "PATH"),
    "demdiff DEM_A": (["demdiff", "{X}", "{b}", "--out", "{O}"], "DEMS"),
    "demdiff DEM_B": (["demdiff", "{a}", "{X}", "--out", "{O}"], "DEMS"),
    "demdiff --stable-mask": (["demdiff", "{a}", "{b}", "--out", "{O}", "--stable-mask", "{X}"], "--stable-mask"),
    "demdiff --footprints": (["demdiff", "{a}", "{b}", "--out", "{O}", "--footprints", "{X}"], "--footprints"),
    "demdiff --base": (["demdiff", "{a}", "{b}", "--out", "{O}", "--base", "{X}"], "--base"),
    "consistency PAIR_DEMS": (["consistency", "{X}", "{pa}", "--out", "{O}/m.json"], "PAIR_DEMS"),
    "change --pair-dem-a": (
        ["change", "--pair-dem-a", "{X}", "--pair-dem-b", "{pb}", "--model", "{model}", "--out", "{O}"],
        "--pair-dem-a",
    ),
    "change --pair-dem-b": (
        ["change", "--pair-dem-a", "{pa}", "--pair-dem-b", "{X}", "--model", "{model}", "--out", "{O}"],
        "--pair-dem-b",
    ),
    "change --dem-a": (
        ["change", "--dem-a", "{X}", "--pair-dem-b", "{pb}", "--model", "{model}", "--out", "{O}"],
        "--dem-a",
    ),
    "change --dem-b": (
        ["change", "--pair-dem-a", "{pa}", "--dem-b", "{X}", "--model", "{model}", "--out", "{O}"],
        "--dem-b",
    ),
    "change --model": (
        ["change", "--pair-dem-a", "{pa}", "--pair-dem-b", "{pb}", "--model", "{X}", "--out", "{O}"],
        "--model",
    ),
    "change --footprints": (
        [
            "change",
            "--pair-dem-a",
            "{pa}",
            "--pair-dem-b",
            "{pb}",
            "--model",
            "{model}",
            "--out",
            "{O}",
            "--footprints",
            "{X}",
        ],
        "--footprints",
    ),
    "run MANIFEST": (["run", "{X}", "--out", "{O}"], "MANIFEST"),
    "run --model": (["run", "{m}", "--out", "{O}", "--model", "{X}"], "--model"),
    "run --config": (["run", "{m}", "--out", "{O}", "--model", "{model}", "--config", "{X}"], "--config"),
    "run --footprints": (["run", "{m}", "--out", "{O}", "--model", "{model}", "--footprints", "{X}"], "--footprints"),
    "run --screen-weights": (
        [
            "run",
            "{m}",
            "--out",
            "{O}",
            "--model",
            "{model}",
            "--screen",
            "--screen-feature",
            "cnn",
            "--screen-backbone",
            "efficientnet_lite0",
            "--screen-weights",
            "{X}",
        ],
        "--screen-weights",
    ),
    "stereo INPUTS": (["stereo", "{X}", "--out", "{O}"], "INPUTS"),
    "probchange MANIFEST": (["probchange", "{X}", "--out", "{O}"], "MANIFEST"),
    "mpp MANIFEST": (["mpp", "{X}", "--out", "{O}"], "MANIFEST"),
    "mpp --image-a": (["mpp", "--image-a", "{X}", "--image-b", "{b}", "--out", "{O}"], "--image-a"),
    "mpp --image-b": (["mpp", "--image-a", "{a}", "--image-b", "{X}", "--out", "{O}"], "--image-b"),
    "mpp --dsm-a": (["mpp", "{m}", "--dsm-a", "{X}", "--dsm-b", "{sdem}", "--out", "{O}"], "--dsm-a"),
    "mpp --dsm-b": (["mpp", "{m}", "--dsm-a", "{sdem}", "--dsm-b", "{X}", "--out", "{O}"], "--dsm-b"),
    "mpp --ground": (
        [
            "mpp",
            "--image-a",
            "{a}",
            "--image-b",
            "{b}",
            "--dsm-a",
            "{a}",
            "--dsm-b",
            "{b}",
            "--ground",
            "{X}",
            "--out",
            "{O}",
        ],
        "--ground",
    ),
    "mpp --change-prior": (["mpp", "{m}", "--change-prior", "{X}", "--out", "{O}"], "--change-prior"),
    "ortho SOURCE": (["ortho", "{X}", "--dsm", "{sdem}", "--out", "{O}"], "SOURCE"),
    "ortho --camera": (["ortho", "{img}", "--dsm", "{sdem}", "--camera", "{X}", "--out", "{O}"], "--camera"),
    "screen A": (["screen", "{X}", "{b}", "--out", "{O}"], "SOURCES"),
    "screen B": (["screen", "{a}", "{X}", "--out", "{O}"], "SOURCES"),
    "screen --weights": (
        [
            "screen",
            "{a}",
            "{b}",
            "--feature",
            "cnn",
            "--backbone",
            "efficientnet_lite0",
            "--weights",
            "{X}",
            "--out",
            "{O}",
        ],
        "--weights",
    ),
    "screen --nochange": (
        ["screen", "{a}", "{b}", "--nochange", "{X}", "--nochange", "{a}", "--out", "{O}"],
        "--nochange",
    ),
    "import-cameras SOURCES": (["import-cameras", "{X}", "--out", "{O}"], "SOURCES"),
    "landcover train --labels": (
        ["landcover", "train", "--labels", "{X}", "--image", "{img}", "--out", "{O}/m.joblib"],
        "--labels",
    ),
    "landcover train --image": (
        ["landcover", "train", "--labels", "{labels}", "--image", "{X}", "--out", "{O}/m.joblib"],
        "--image",
    ),
    "landcover predict --model": (
        ["landcover", "predict", "--model", "{X}", "--image", "{img}", "--out", "{O}"],
        "--model",
    ),
    "landcover integrate --detailed": (
        ["landcover", "integrate", "--detailed", "{X}", "--manifest", "{m}", "--out", "{O}"],
        "--detailed",
    ),
    "volume update MODEL_DIR --manifest": (["volume", "update", "{O}/model", "--manifest", "{X}"], "--manifest"),
    "volume detect MODEL_DIR": (["volume", "detect", "{X}", "{img}", "--out", "{O}"], "MODEL_DIR"),
    "volume render MODEL_DIR": (["volume", "render", "{X}", "--image", "{img}", "--out", "{O}"], "MODEL_DIR"),
    "synth --params": (["synth", "--tiny", "--out", "{O}", "--params", "{X}"], "--params"),
}

#: slots where a folder is a valid input (a scene folder, a model folder): the folder case expects a refusal of
#: its content (an empty folder), still one clean error
FOLDER_OK = {
    "info PATH",
    "run MANIFEST",
    "stereo INPUTS",
    "probchange MANIFEST",
    "mpp MANIFEST",
    "import-cameras SOURCES",
    "volume detect MODEL_DIR",
    "volume render MODEL_DIR",
}


class _Hang(Exception):
    pass


def _bad_file(kind: str, folder: Path, slot: str) -> Path:
    name = {
        "PATH": "x.tif",
        "MANIFEST": "scene.yaml",
        "--config": "run_config.json",
        "--model": "model.json",
        "--params": "params.json",
        "--camera": "x_rpc.txt",
        "--weights": "w.pth",
        "--screen-weights": "w.pth",
        "--labels": "labels.gpkg",
        "--footprints": "fp.gpkg",
        "SOURCES": "x.tif",
    }.get(slot, "x.tif")
    if slot == "MODEL_DIR" and kind != "folder":
        name = "model"
    p = folder / f"bad_{kind}" / name
    p.parent.mkdir(parents=True, exist_ok=True)
    if kind == "empty":
        p.write_bytes(b"")
    elif kind == "garbage":
        p.write_bytes(bytes((i * 97 + 13) % 256 for i in range(4096)))
    elif kind == "folder":
        p.mkdir()
    elif kind == "fifo":
        os.mkfifo(p)
    return p


OUTCOMES: dict[str, str] = {}


def _outcome(r, bad: Path) -> str:
    errs = error_lines(r.stderr)
    if r.exit_code == 0:
        return "exit 0 (wrong answer)"
    if "Traceback" in r.output:
        return "traceback"
    if any("internal error" in e for e in errs):
        return "internal error"
    if r.exit_code != 2 or len(errs) != 1:
        return f"exit {r.exit_code}, {len(errs)} error line(s)"
    return "clean error"


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("slot", sorted(SLOTS))
@pytest.mark.slow
def test_every_command_refuses_a_bad_file(slot, kind, fx, tmp_path):
    template, name = SLOTS[slot]
    bad = _bad_file(kind, tmp_path, name)
    out = tmp_path / "O"
    values = {
        "X": bad,
        "O": out,
        "a": fx.a,
        "b": fx.b,
        "m": fx.scene.manifest,
        "fp": fx.fp,
        "img": fx.scene.files[0],
        "sdem": fx.scene.root / "dem.tif",
        "pa": fx.pa,
        "pb": fx.pb,
        "labels": fx.labels,
        "model": REPO / "examples/kahramanmaras/marseille_urban_model.json",
    }
    args = [a.format(**values) for a in template]
    before = sha256_tree([fx.root])

    def alarm(signum, frame):
        raise _Hang(f"{slot} with a {kind} ran past {HANG_S} s")

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(HANG_S)
    try:
        r = CliRunner().invoke(main, ["--progress", "none", *args])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    if isinstance(r.exception, _Hang):
        OUTCOMES[f"{slot} / {kind}"] = "hang"
        pytest.fail(str(r.exception))
    OUTCOMES[f"{slot} / {kind}"] = got = _outcome(r, bad)
    assert got == "clean error", f"{got}:\n{r.output}"
    err = error_lines(r.stderr)[0]
    # the error is about the bad input: it names the file (or, for a folder input, its folder)
    assert (
        bad.name in err or str(bad) in err or str(bad.parent) in err or kind == "missing" and "does not exist" in err
    ), err
    assert not part_files(tmp_path) and sha256_tree([fx.root]) == before
    if out.exists():
        left = [p for p in out.rglob("*") if p.is_file() and not p.name.startswith(("geocd_", ".geocd"))]
        assert not left, f"files written by a failed run: {left}"


def test_every_file_input_is_listed():
    """Each command's path arguments and input path options have a slot (outputs excepted)."""
    import click

    outputs = {"--out", "--plot", "--pictures", "--profile", "--image-dir"}
    ctx = click.Context(main)
    named = {
        (s.split()[0] if not s.startswith(("volume", "landcover")) else " ".join(s.split()[:2]), n)
        for s, (_, n) in SLOTS.items()
    }
    missing = []
    from geocd.cli import SUBCOMMANDS

    def walk(cmd, path):
        if isinstance(cmd, click.Group):
            for n, sub in cmd.commands.items():
                walk(sub, [*path, n])
            return
        for p in cmd.params:
            if not isinstance(p.type, click.Path):
                continue
            flag = p.opts[0] if isinstance(p, click.Option) else p.human_readable_name
            if flag in outputs or flag.startswith("--labelled"):
                continue
            if (" ".join(path), flag) not in named and not any(
                (" ".join(path), f) in named for f in getattr(p, "opts", [])
            ):
                missing.append(f"{' '.join(path)} {flag}")

    for n in sorted(SUBCOMMANDS):
        walk(main.get_command(ctx, n), [n])
    # inputs deliberately not in the matrix: a second copy of a slot's check, or an optional extra of a method
    extra_ok = {
        "landcover predict --image",
        "landcover predict --manifest",
        "landcover predict --dem",
        "landcover predict --footprints",
        "landcover predict --dsm",
        "landcover train --manifest",
        "landcover train --dem",
        "landcover train --footprints",
        "landcover train --dsm",
        "landcover integrate --manifest",
        "landcover integrate --dem",
        "landcover integrate --footprints",
        "landcover integrate --dsm",
        "landcover integrate --coarse",
        "landcover integrate --truth",
        "landcover integrate --exclude-labels",
        "volume update MODEL_DIR",
        "volume update --image",
        "volume detect --camera",
        "volume detect --shadow-dsm",
        "volume detect IMAGE",
        "volume render --image",
        "volume detect --out",
        "volume render --out",
    }
    assert set(missing) <= extra_ok, sorted(set(missing) - extra_ok)
