"""``python -m bench.peers``: the README's table is what ``--readme`` renders from the committed JSON, the JSON
holds every row with a peer figure or the reason it has none, and ``--list`` / ``--dry-run`` work. No timing is
asserted and no peer is needed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from bench.figures.registry import by_name as figure_entries
from bench.peers.__main__ import main
from bench.peers.report import JSON, README, load, readme_block, render, series, verdict
from bench.peers.rows import GROUPS, ROWS, by_name, groups_for

REPO = Path(__file__).resolve().parents[1]
VERDICTS = {"goal met", "short", "blocked", "no goal"}


@pytest.fixture(scope="module")
def doc() -> dict:
    assert JSON.is_file(), "bench/results/peers.json is committed (python -m bench.peers writes it)"
    return load(JSON)


def test_readme_block_is_what_readme_renders_from_the_committed_json(doc):
    block = readme_block(README.read_text(encoding="utf-8"))
    assert block is not None, "README.md has the <!-- peers:begin --> … <!-- peers:end --> block"
    assert block == render(doc), "run: python -m bench.peers --readme --no-measure"
    assert main(["--check-readme", "--no-measure"]) == 0


def test_readme_stays_short_and_quotes_no_stale_figures():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 150
    for page in [README, *sorted((REPO / "docs").rglob("*.md"))]:
        t = page.read_text(encoding="utf-8")
        assert "+1.889 ± 0.256" not in t and "38.6×" not in t, page


def test_json_has_every_row_with_its_figures_or_the_reason(doc):
    rows = {r["name"]: r for r in doc["rows"]}
    assert [r["name"] for r in doc["rows"]] == [r.name for r in ROWS if r.name in rows]
    assert set(rows) == set(by_name()), "every row of bench/peers/rows.py measured"
    for name, rec in rows.items():
        row = by_name()[name]
        assert rec["what"] == row.what and rec["goal"] == row.goal, name
        assert rec["verdict"] in VERDICTS, name
        assert re.fullmatch(r"\d{4}-\d\d-\d\d", rec["date"]), name
        m = rec["machine"]
        assert m["cores"] >= 1 and len(m["loadavg_start"]) == 3 and len(m["loadavg_end"]) == 3, name
        assert rec["repeat"] >= 3 and rec["command"].startswith("python -m bench.peers"), name
        # data relative to the shared data folder, commands without this machine's folders
        assert all(not d.startswith("/") for d in rec["data"]), name
        assert rec["commands"] and all("/tmp" not in str(c) and "/root" not in str(c) for c in rec["commands"].values())
        g = rec["geocd"]
        if rec["verdict"] == "blocked" and not g["n"]:
            assert rec["reason"], name
            continue
        assert g["n"] >= 3 and g["cpu_s"]["min"] <= g["cpu_s"]["median"], name
        assert g["wall_s"]["min"] <= g["wall_s"]["median"], name
        # a peer figure measured in the same run, or the reason there is none (no invented number)
        if rec["peer"] is None:
            assert rec["reason"] and rec["ratio"] is None and rec["verdict"] == "blocked", name
        else:
            p = rec["peer"]
            assert p["n"] >= 3 and p["cpu_s"]["median"] > 0 and p["label"], name
            num, den = (g, p) if row.peer is None else (p, g)
            assert rec["ratio"]["cpu"] == pytest.approx(num["cpu_s"]["median"] / den["cpu_s"]["median"]), name
            assert rec["verdict"] == verdict(row, rec), name


def test_a_row_without_its_peer_says_why_and_has_no_figure():
    row = by_name()["stereo_cars"]
    rec = {
        "name": row.name,
        "what": row.what,
        "goal": row.goal,
        "geocd": series([{"cpu_s": 10.0, "wall_s": 20.0, "returncode": 0}] * 3, "geocd warm"),
        "peer": None,
        "reason": "not installed",
        "ratio": None,
        "accuracy": {"ok": None},
        "date": "2000-01-01",
        "machine": {"cores": 2, "loadavg_start": [1.0, 1.0, 1.0]},
        "repeat": 3,
        "command": "python -m bench.peers",
    }
    rec["verdict"] = verdict(row, rec)
    assert rec["verdict"] == "blocked"
    line = render({"rows": [rec]}).splitlines()[-1]
    assert "none: not installed" in line and "| — |" in line


def test_list_names_every_row_and_the_figures_registry_has_the_run(capsys):
    assert main(["--list"]) == 0
    out = capsys.readouterr().out
    for r in ROWS:
        assert r.name in out
    assert f"{len(ROWS)} rows in {len(GROUPS)} groups" in out
    e = figure_entries()["peers"]
    assert not e.pictures and e.tables and any("bench.peers" in " ".join(s) for s in e.steps)


def test_dry_run_prints_every_groups_commands(capsys, tmp_path):
    assert main(["--dry-run", "--work", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for g in GROUPS:
        assert f"[{g}]" in out
    assert "cars" in out and "xdem" in out and "--first gdal" in out and "stereo" in out
    assert not list(tmp_path.iterdir()), "a dry run writes nothing"
    assert groups_for(["stereo_cold", "rpc_warm"]) == ["rpc", "stereo"]
    with pytest.raises(SystemExit):
        groups_for(["no_such_row"])
