"""bench/eval_building_change.py: the scoring on tiny synthetic masks, pooling, the table, and the commands it runs
(``--dry-run``; no method is run, in this process)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import eval_building_change as ebc  # noqa: E402
from tests.conftest import shared_data  # noqa: E402


def _masks():
    label = np.zeros((40, 40), bool)
    label[2:10, 2:10] = True  # 64 cells: an object
    label[20:28, 20:28] = True  # 64 cells: an object
    label[35:38, 35:38] = True  # 9 cells: too small to be an object, but counts in the pixels
    mask = np.zeros_like(label)
    mask[2:10, 2:9] = True  # covers 56 of the first object: found
    mask[30:33, 2:5] = True  # 9 cells off the label: a false detection
    return mask, label


def test_score_pair_pixels_and_objects():
    mask, label = _masks()
    s = ebc.score_pair(mask, label)
    assert (s["tp"], s["fp"], s["fn"]) == (56, 9, 137 - 56)
    assert s["precision"] == pytest.approx(56 / 65, abs=1e-4)
    assert s["recall"] == pytest.approx(56 / 137, abs=1e-4)
    assert (s["label_objects"], s["missed"], s["found"]) == (2, 1, 1)
    assert (s["detected"], s["false"], s["true"]) == (2, 1, 1)


def test_score_pair_empty_and_shape_mismatch():
    z = np.zeros((8, 8), bool)
    s = ebc.score_pair(z, z)
    assert s["f1"] == 0.0 and s["label_objects"] == 0 and s["detected"] == 0
    with pytest.raises(ValueError):
        ebc.score_pair(z, np.zeros((8, 9), bool))


def test_pool_sums_counts_and_object_f1():
    mask, label = _masks()
    r = dict(ebc.score_pair(mask, label), cpu_s=2.0, wall_s=3.0)
    p = ebc.pool([r, r])
    assert p["pairs"] == 2 and p["tp"] == 112 and p["label_objects"] == 4
    assert p["precision"] == r["precision"] and p["f1"] == r["f1"]
    assert p["object_precision"] == 0.5 and p["object_recall"] == 0.5 and p["object_f1"] == 0.5
    assert p["cpu_s_mean"] == 2.0
    doc = {"command": "x", "summary": {"screen": {"a": p, "all": p}}, "screen_rules": {"a": "rule"}}
    md = ebc.render(doc)
    assert "| **pooled** | 2 |" in md and "* a: rule" in md


def test_commands_use_no_label_of_the_scored_set():
    pair = {"set": "whucd", "name": "x", "a": Path("A/x.png"), "b": Path("B/x.png"), "pixel": 0.3}
    mpp = ebc.command(pair, "mpp", Path("o"))
    assert mpp[:2] == ["geocd", "mpp"] and mpp[mpp.index("--pixel-size") + 1] == "0.3"
    for s in ebc.SETS:
        scr = ebc.command(dict(pair, set=s), "screen", Path("o"))
        used = [a for a in scr if a.endswith(".png")][2:]  # the rule's files
        assert used and all(str(ebc.SETS[s][0]) not in u for u in used)
        assert ("--labelled" in scr) != ("--nochange" in scr)


def test_help(capsys):
    with pytest.raises(SystemExit) as e:
        ebc.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--quick" in out and "--dry-run" in out


@pytest.mark.realdata
def test_dry_run_lists_the_commands(capsys, tmp_path):
    for folder, _, _ in ebc.SETS.values():
        shared_data(*folder.relative_to(ebc.DATA).parts, "A")
    assert ebc.main(["--dry-run", "--quick", "--work", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    # one pair per set: the screen on 4 sets, the MPP on the 3 building sets
    assert sum(" screen " in x for x in lines) == 4 and sum(" mpp " in x for x in lines) == 3
    assert all("train_386" not in x.split("--")[0] for x in lines)  # the control crop is never the quick pair
