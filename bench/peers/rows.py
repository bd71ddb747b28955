"""The rows of the side-by-side table: what each measures, against which peer, and its goal (issues 45 and 46).

A row's *ratio* is always of median CPU seconds: the peer's over geocd's for a row against a peer (the speed-up,
goal "≥ k×"), cold over warm for a cold-start row (goal "≤ k×"). Rows are measured in groups that share runs
(:mod:`bench.peers.measure`): one geocd stereo run is both the warm figure against CARS and the warm half of the
cold/warm row.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Row:
    """One row of the table.

    Attributes
    ----------
    name : str
        Its key (``--only NAME``).
    group : str
        The measuring group that makes it (rows of a group share runs).
    what : str
        What is measured, for the table.
    peer : str or None
        The peer's key (:data:`bench.peers.install.PEERS`, or ``gdal``); None: geocd warm is the baseline.
    goal : str
        The goal in words.
    op : str or None
        ``>=`` or ``<=``: how the ratio must stand against ``target``; None: the row has no goal.
    target : float
        The goal's ratio.
    accuracy_goal : str
        The accuracy condition that must also hold ("" when none).
    data : tuple of str
        Files it reads, relative to the shared data folder (``../shared/data``).
    minutes : float
        Wall minutes of its group with ``--repeat 3`` on the 2-core development host (the first row of a group
        carries the group's; as a full run took them).
    """

    name: str
    group: str
    what: str
    peer: str | None
    goal: str
    op: str | None
    target: float
    accuracy_goal: str
    data: tuple[str, ...]
    minutes: float


PAIR = ("s2p_pleiades/input_pair/img_01.tif", "s2p_pleiades/input_pair/img_02.tif")
S2P_DSM = "s2p_pleiades/expected_output/pair/dsm.tif"
MSH_BASE = "usgs_msh_dome_dems/raw_e00/1_msh00_83.e00"


def _msh(a: int, b: int) -> tuple[str, ...]:
    return (f"usgs_msh_dome_dems/geotiff_utm10n/{a}.tif", f"usgs_msh_dome_dems/geotiff_utm10n/{b}.tif", MSH_BASE)


ROWS: tuple[Row, ...] = (
    Row(
        "stereo_cars",
        "stereo",
        "Stereo, Pléiades Réunion pair (whole overlap), whole process, warm",
        "cars",
        "≥ 10× CPU at NMAD ≤ CARS's",
        ">=",
        10.0,
        "NMAD vs s2p's DSM of geocd's DSM as written (valid + filled cells, like CARS's filled DSM) ≤ CARS's",
        (*PAIR, S2P_DSM),
        25.0,
    ),
    Row(
        "stereo_cold",
        "stereo",
        "Stereo, same pair, cold (empty numba cache) / warm",
        None,
        "cold ≤ 2× warm",
        "<=",
        2.0,
        "the same DSM cold and warm",
        (*PAIR, S2P_DSM),
        0.0,
    ),
    Row(
        "run_cold",
        "run",
        "`geocd run sample_aoi`, cold / warm",
        None,
        "cold ≤ 1.5× warm",
        "<=",
        1.5,
        "the same run_summary.json figures cold and warm",
        (),
        10.0,
    ),
    Row(
        "demdiff_26_27",
        "demdiff_26_27",
        "DEM difference, Mount St Helens 26 → 27, in process (same inputs and masks)",
        "xdem",
        "≥ 5× CPU, volumes within σ",
        ">=",
        5.0,
        "|volume geocd − xDEM| ≤ 1σ (combined; geocd's σ alone when xDEM has none)",
        _msh(26, 27),
        1.6,
    ),
    Row(
        "demdiff_26_27_process",
        "demdiff_26_27",
        "DEM difference, MSH 26 → 27, whole process (`geocd demdiff --base`, warm)",
        "xdem",
        "≥ 5× CPU",
        ">=",
        5.0,
        "",
        _msh(26, 27),
        0.0,
    ),
    Row(
        "demdiff_2_27",
        "demdiff_2_27",
        "DEM difference, MSH 2 → 27, in process (same inputs and masks)",
        "xdem",
        "≥ 5× CPU, volumes within σ",
        ">=",
        5.0,
        "|volume geocd − xDEM| ≤ 1σ (combined; geocd's σ alone when xDEM has none)",
        _msh(2, 27),
        0.7,
    ),
    Row(
        "demdiff_2_27_process",
        "demdiff_2_27",
        "DEM difference, MSH 2 → 27, whole process (`geocd demdiff --base`, warm)",
        "xdem",
        "≥ 5× CPU",
        ">=",
        5.0,
        "",
        _msh(2, 27),
        0.0,
    ),
    Row(
        "rpc_cold",
        "rpc",
        "First RPC localization of 1e6 points in a new process, cold (empty numba cache)",
        "gdal",
        "cold ≤ GDAL (ratio ≥ 1×)",
        ">=",
        1.0,
        "",
        (PAIR[0],),
        1.6,
    ),
    Row(
        "rpc_warm",
        "rpc",
        "First RPC localization of 1e6 points in a new process, warm",
        "gdal",
        "(no goal: beside the cold row)",
        None,
        0.0,
        "",
        (PAIR[0],),
        0.0,
    ),
)

#: the groups in the order a full run measures them (quick ones first)
GROUPS: tuple[str, ...] = ("rpc", "demdiff_26_27", "demdiff_2_27", "run", "stereo")


def by_name() -> dict[str, Row]:
    """{row name: row}."""
    return {r.name: r for r in ROWS}


def rows_of(group: str) -> list[Row]:
    """The rows a group makes."""
    return [r for r in ROWS if r.group == group]


def groups_for(only: list[str]) -> list[str]:
    """The groups to run for ``--only`` (row or group names; all when empty), in :data:`GROUPS` order."""
    if not only:
        return list(GROUPS)
    names = by_name()
    want = set()
    for o in only:
        if o in GROUPS:
            want.add(o)
        elif o in names:
            want.add(names[o].group)
        else:
            raise SystemExit(f"no row or group {o!r}: see python -m bench.peers --list")
    return [g for g in GROUPS if g in want]
