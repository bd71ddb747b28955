"""``geocd demdiff``: DEM-vs-DEM change (two DEMs, a list or a manifest for a time series)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import click

from .common import check_confidence, dask_options
from .vocabulary import vertical_datum_option

DEM_LIST_HELP = """DEMS: two DEM files (A = reference/earlier, B = later), three or more (a time series, in date
order or with --dates), or ONE list file (.txt/.csv: one `path[,date[,name]]` per line, # comments) or geocd manifest
(.yaml/.json, epochs with a `dem:`)."""


#: two DEMs on a grid of more cells than this are processed tile by tile unless --untiled
TILED_ABOVE_CELLS = 16_000_000


def _use_tiles(ents, tiled: bool | None, tiling_opts: dict, base) -> bool:
    """Whether a DEM comparison runs tile by tile (``--tiled``, a tiling option, or a large grid)."""
    from ..errors import ConfigError

    asked = tiled is True or (tiled is None and bool(tiling_opts))
    if tiled is False:
        if tiling_opts:
            raise ConfigError(f"--untiled with tiling options ({', '.join(sorted(tiling_opts))}); drop one of them")
        return False
    if len(ents) != 2:
        if asked:
            raise ConfigError(
                "tiled processing compares two DEMs; a time series runs untiled (drop --tiled and the tiling options)"
            )
        return False
    if any(Path(p).suffix.lower() == ".e00" for p, *_ in ents):
        if asked:
            raise ConfigError(
                "tiled processing reads GDAL rasters; convert the .e00 DEM to GeoTIFF first "
                "(the base DEM may stay an .e00)"
            )
        return False
    if asked:
        return True
    from ..io.raster import _open

    with _open(ents[0][0]) as ds:
        return ds.width * ds.height > TILED_ABOVE_CELLS


def _demdiff_tiled(
    ctx,
    sess,
    ents,
    out_dir,
    prefix,
    params,
    tiling_opts,
    stable_mask,
    mask_is,
    footprints,
    datum_a,
    datum_b,
    base,
    no_plots,
    nodata,
) -> None:
    """Two DEMs tile by tile (geocd.demdiff.tiled): the same products as the untiled run."""
    from ..demdiff.tiled import dem_difference_tiled
    from ..tiling.params import TilingParams
    from . import emit_result, make_progress

    tiling = TilingParams(**tiling_opts)
    progress = make_progress(ctx, "demdiff")
    try:
        (pa, _, na, va), (pb, _, nb, vb) = ents
        sess.note(
            f"tiled run: tiles of {tiling.tile_size} cells, scheduler {tiling.scheduler}; a killed run "
            "restarted with the same command resumes"
        )
        res = dem_difference_tiled(
            pa,
            pb,
            out_dir,
            params=params,
            tiling=tiling,
            stable_mask=stable_mask,
            mask_is=mask_is,
            footprints=footprints,
            epoch_a=na,
            epoch_b=nb,
            datum_a=va or datum_a,
            datum_b=vb or datum_b,
            base=base,
            prefix=prefix,
            plots=not no_plots,
            progress=progress,
            nodata=nodata,
            provenance={"dem_a": pa, "dem_b": pb, "stable_mask": stable_mask, "base": base},
        )
    finally:
        if hasattr(progress, "close"):
            progress.close()
    s = res.summary
    for n in res.notes:
        if n != res.coreg.summary():
            sess.note(n)
    for w in res.warnings:
        sess.warn(w)
    sess.say(res.coreg.summary())
    credible = (
        ""
        if res.status != "degenerate_stable_terrain"
        else " — NOT CREDIBLE: degenerate stable terrain, see the warning"
    )
    sess.say(
        f"stable NMAD {s['stable_nmad_m']:.2f} m on {s['n_stable']} cells; changed at "
        f"{params.confidence:g}%: {s['changed_area_m2'] / 1e6:.4f} km², volume "
        f"{s['volume_changed_m3'] / 1e6:+.4f} ± {s['volume_changed_sigma_m3'] / 1e6:.4f} Mm³ (1σ)" + credible
    )
    sess.say(
        f"tiled: {res.passes} passes, {res.tiles_resumed} tile results resumed, "
        f"{'exact (every cell in every statistic)' if res.exact else 'whole-scene statistics on a fixed subsample'}"
    )
    sess.data(
        status=res.status,
        tiled=True,
        passes=res.passes,
        tiles_resumed=res.tiles_resumed,
        **{
            k: s[k]
            for k in (
                "stable_nmad_m",
                "n_stable",
                "changed_area_m2",
                "volume_changed_m3",
                "volume_changed_sigma_m3",
                "shift_applied_m",
                "stable_identical_fraction",
                "wall_s",
            )
            if k in s
        },
    )
    emit_result(ctx, res.outputs)


def _read_dem(path: str, datum: str | None, nodata: float | None = None):
    from ..io.raster import read_dem

    if Path(path).suffix.lower() == ".e00":
        from ..io.e00 import read_e00_dem

        return read_e00_dem(path, vertical_datum=datum)
    return read_dem(path, vertical_datum=datum, nodata=nodata)


def _parse_list(path: Path) -> list[tuple[str, _dt.date | None, str]]:
    from ..errors import ManifestError

    out = []
    for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = [p.strip() for p in s.replace("\t", ",").split(",")]
        p = Path(parts[0])
        if not p.is_absolute():
            p = path.parent / p
        date = None
        if len(parts) > 1 and parts[1]:
            try:
                date = _dt.date.fromisoformat(parts[1].replace("_", "-"))
            except ValueError:
                raise ManifestError(f"{path}:{k}: cannot read {parts[1]!r} as a date; use YYYY-MM-DD") from None
        name = parts[2] if len(parts) > 2 and parts[2] else p.stem
        out.append((str(p), date, name))
    if len(out) < 2:
        raise ManifestError(f"{path} lists {len(out)} DEM(s); a comparison needs at least two")
    return out


def _entries(dems: tuple[str, ...], dates: str | None, names: str | None):
    """→ list of (path, date, name, vertical datum or None)."""
    from ..errors import ConfigError, InputFileNotFoundError

    if len(dems) == 1:
        p = Path(dems[0])
        if not p.exists():
            raise InputFileNotFoundError(f"{p} does not exist; check the path")
        if p.suffix.lower() in (".yaml", ".yml", ".json"):
            from ..io.manifest import load_manifest

            m = load_manifest(p)
            ents = [(str(e.dem.path), e.date, e.name, e.dem.vertical_datum) for e in m.epochs if e.dem is not None]
            if len(ents) < 2:
                from ..errors import ManifestError

                raise ManifestError(f"{p} has {len(ents)} epoch(s) with a `dem:`; DEM differencing needs two or more")
            return ents
        if p.suffix.lower() in (".txt", ".csv", ".lst", ".list"):
            ents = [(a, b, c, None) for a, b, c in _parse_list(p)]
            _check_dates_in_order(ents, str(p))
            return ents
        raise ConfigError(f"give two DEMs, or one list (.txt/.csv) or manifest (.yaml/.json); got only {p}")
    ents = [(d, None, Path(d).stem, None) for d in dems]
    if dates:
        ds = [s.strip() for s in dates.split(",")]
        if len(ds) != len(ents):
            raise ConfigError(f"--dates lists {len(ds)} dates for {len(ents)} DEMs")
        try:
            ents = [(p, _dt.date.fromisoformat(d), n, v) for (p, _, n, v), d in zip(ents, ds)]
        except ValueError as exc:
            raise ConfigError(f"--dates: {exc}; use YYYY-MM-DD") from None
    if names:
        ns = [s.strip() for s in names.split(",")]
        if len(ns) != len(ents):
            raise ConfigError(f"--names lists {len(ns)} names for {len(ents)} DEMs")
        ents = [(p, d, n, v) for (p, d, _, v), n in zip(ents, ns)]
    _check_dates_in_order(ents, "--dates")
    return ents


def _check_dates_in_order(ents, where: str) -> None:
    """DEMs are compared oldest to newest: a later DEM dated before an earlier one would flip every sign."""
    from ..errors import ConfigError

    for (p0, d0, n0, _), (p1, d1, n1, _) in zip(ents, ents[1:]):
        if d0 is not None and d1 is not None and d1 < d0:
            raise ConfigError(
                f"{where}: {n1} ({d1}) is listed after {n0} ({d0}) but dated before it; list the "
                "DEMs from oldest to newest (change is measured from each DEM to the next)"
            )


@click.command(
    "demdiff", help="Height change between DEMs, with co-registration and honest uncertainty.\n\n" + DEM_LIST_HELP
)
@click.argument("dems", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: ./geocd_out/<A>__<B>, or ./geocd_out/<list name> for a series).",
)
@click.option("--prefix", default="demdiff", show_default=True, help="Prefix of the output file names.")
@click.option(
    "--stable-mask",
    type=click.Path(path_type=str),
    default=None,
    help="Stable terrain: a raster (non-zero = inside) or polygons (inside). Default: automatic.",
)
@click.option(
    "--mask-is",
    type=click.Choice(["stable", "unstable"]),
    default="stable",
    show_default=True,
    help="Whether --stable-mask marks stable terrain or unstable areas (e.g. glacier outlines).",
)
@click.option(
    "--footprints",
    type=click.Path(path_type=str),
    default=None,
    help="Building footprints: excluded from stable terrain and attributed (layer `buildings`).",
)
@click.option(
    "--confidence",
    type=float,
    default=95.0,
    show_default=True,
    callback=check_confidence,
    help="Confidence level in percent at which cells are called changed.",
)
@vertical_datum_option(
    "Vertical datum of DEMs whose files do not say (ellipsoid, egm96, egm2008): once for every DEM, or twice: "
    "DEM A's, then DEM B's (and every later series DEM's); 'file' keeps what a DEM's file says "
    "(--vertical-datum file --vertical-datum egm96: B only).",
    multiple=True,
)
@click.option("--datum-a", default=None, hidden=True, help="Old spelling of the first --vertical-datum.")
@click.option("--datum-b", default=None, hidden=True, help="Old spelling of the second --vertical-datum.")
@click.option(
    "--resampling",
    type=click.Choice(["nearest", "bilinear", "cubic", "average"]),
    default="bilinear",
    show_default=True,
    help="How DEM B is resampled onto A's grid.",
)
@click.option("--no-coreg", is_flag=True, help="Do not co-register (compare the DEMs as they are).")
@click.option("--tilt", is_flag=True, help="Also remove a planar vertical tilt after the shift.")
@click.option(
    "--on-underconstrained",
    type=click.Choice(["vertical_only", "apply", "none", "raise"]),
    default="vertical_only",
    show_default=True,
    help="What to do when the co-registration fit is under-constrained.",
)
@click.option("--min-region-cells", type=int, default=4, show_default=True, help="Smallest changed region kept.")
@click.option(
    "--region-test",
    type=click.Choice(["noise", "off"]),
    default="noise",
    show_default=True,
    help="noise: keep a changed region only when its combined evidence beats the regions that noise alone "
    "forms (simulated from the fitted error model and variogram) at --confidence; off: every region.",
)
@click.option(
    "--fallback-threshold",
    type=float,
    default=None,
    help="|dh| (m) that marks change when no stable terrain exists (no significance then).",
)
@click.option(
    "--base",
    type=click.Path(path_type=str),
    default=None,
    help="Base DEM the DEMs were merged onto (e.g. an .e00): each epoch's survey is where it differs from "
    "the base; comparisons use only the shared survey area (two DEMs or a series); a series also gets "
    "base → epoch volumes.",
)
@click.option("--dates", default=None, help="Comma-separated dates (YYYY-MM-DD) of the DEMs given as arguments.")
@click.option("--names", default=None, help="Comma-separated epoch names of the DEMs given as arguments.")
@click.option("--pair-products", is_flag=True, help="For a series, also write every interval's rasters and layers.")
@click.option("--no-plots", is_flag=True, help="Do not draw PNG plots.")
@click.option(
    "--tiled/--untiled",
    default=None,
    help="Process two DEMs tile by tile (bounded memory, resumable after a kill, on Dask). Default: tiled "
    f"when the grid has more than {TILED_ABOVE_CELLS // 1_000_000} million cells or a tiling option "
    "below is given.",
)
@click.option(
    "--tile-size", type=click.IntRange(64, None), default=None, help="Tiled runs: cells per tile side [1024]."
)
@click.option(
    "--nodata",
    type=float,
    default=None,
    metavar="VALUE",
    help="The DEMs' nodata value where the files do not declare it (e.g. -9999). A DEM holding an "
    "undeclared nodata value is refused without it.",
)
@dask_options
@click.pass_context
def demdiff(
    ctx: click.Context,
    dems,
    out_dir,
    prefix,
    stable_mask,
    mask_is,
    footprints,
    confidence,
    vertical_datum,
    datum_a,
    datum_b,
    resampling,
    no_coreg,
    tilt,
    on_underconstrained,
    min_region_cells,
    region_test,
    fallback_threshold,
    base,
    dates,
    names,
    pair_products,
    no_plots,
    tiled,
    tile_size,
    nodata,
    scheduler,
    workers,
    memory_limit,
) -> None:
    from ..errors import ConfigError
    from .common import require_inputs, resolve_out_dir, session

    if len(vertical_datum) > 2:
        raise ConfigError(
            f"--vertical-datum given {len(vertical_datum)} times; give it once (every DEM) or twice (DEM A, DEM B)"
        )
    for old, new in (("--datum-a", datum_a), ("--datum-b", datum_b)):
        if new is not None:
            session(ctx).note(
                f"{old} is now spelled --vertical-datum (DEM A's, then DEM B's); the old name still works"
            )
    if vertical_datum:
        datum_a, datum_b = datum_a or vertical_datum[0], datum_b or vertical_datum[-1]
    datum_a, datum_b = (None if d is not None and d.strip().lower() == "file" else d for d in (datum_a, datum_b))
    require_inputs(*dems, stable_mask, footprints, base)
    ents = _entries(tuple(dems), dates, names)
    require_inputs(*[e[0] for e in ents])
    if len(ents) == 2:
        default_name = f"{ents[0][2]}__{ents[1][2]}"
    else:
        default_name = Path(dems[0]).stem if len(dems) == 1 else f"{ents[0][2]}__{ents[-1][2]}_series"
    out = resolve_out_dir(out_dir, default_name, create=False)
    out_dir = str(out)
    from ..demdiff import CoregParams, DEMDiffParams, dem_difference
    from ..demdiff.products import write_demdiff_products, write_json, write_timeseries_products
    from ..demdiff.timeseries import Epoch, dem_time_series, survey_footprint
    from ..io.outputs import check_prefix, open_outputs
    from . import emit_result, make_progress

    check_prefix(prefix)
    open_outputs(
        out_dir,
        inputs=[*dems, *[e[0] for e in ents], stable_mask, footprints, base],
        products=(f"{prefix}_*", f"*__*/{prefix}_*"),
        prefix=prefix,
    )
    sess = session(ctx)
    sess.open_log(out)
    params = DEMDiffParams(
        coreg=CoregParams(tilt=tilt, on_underconstrained=on_underconstrained),
        coregister=not no_coreg,
        confidence=confidence,
        min_region_cells=min_region_cells,
        region_test=region_test,
        resampling=resampling,
        fallback_threshold_m=fallback_threshold,
    )
    tiling_opts = {
        k: v
        for k, v in (
            ("scheduler", scheduler),
            ("tile_size", tile_size),
            ("n_workers", workers),
            ("memory_limit", memory_limit),
        )
        if v is not None
    }
    if _use_tiles(ents, tiled, tiling_opts, base):
        _demdiff_tiled(
            ctx,
            sess,
            ents,
            out_dir,
            prefix,
            params,
            tiling_opts,
            stable_mask,
            mask_is,
            footprints,
            datum_a,
            datum_b,
            base,
            no_plots,
            nodata,
        )
        return
    fp = None
    loaded = []
    for k, (path, date, name, vd) in enumerate(ents):
        loaded.append(Epoch(name, date, _read_dem(path, vd or (datum_a if k == 0 else datum_b), nodata)))
    base_ep = Epoch(Path(base).stem, None, _read_dem(base, datum_a, nodata)) if base else None
    if footprints:
        from ..io.vector import read_footprints

        fp = read_footprints(footprints, crs=loaded[0].dem.grid.crs)
    progress = make_progress(ctx, "demdiff")
    outputs: dict = {}
    try:
        if len(loaded) == 2:
            a, b = loaded
            if base_ep is not None:
                from ..demdiff.align import align_dems

                pair = align_dems(a.dem, b.dem, a.dem.grid, resampling=resampling, crop=False)
                bh = align_dems(a.dem, base_ep.dem, a.dem.grid, crop=False).height_b_m
                obs = survey_footprint(pair.height_a_m, bh) & survey_footprint(pair.height_b_m, bh)
                res = dem_difference(
                    pair,
                    observed=obs,
                    stable_mask=stable_mask,
                    mask_is=mask_is,
                    footprints=fp,
                    params=params,
                    epoch_a=a.name,
                    epoch_b=b.name,
                    progress=progress,
                )
            else:
                res = dem_difference(
                    a.dem,
                    b.dem,
                    stable_mask=stable_mask,
                    mask_is=mask_is,
                    footprints=fp,
                    params=params,
                    epoch_a=a.name,
                    epoch_b=b.name,
                    progress=progress,
                )
            outputs = write_demdiff_products(
                out_dir,
                res,
                footprints=fp,
                prefix=prefix,
                plots=not no_plots,
                provenance={"dem_a": ents[0][0], "dem_b": ents[1][0], "stable_mask": stable_mask, "base": base},
            )
            s = res.summary
            progress.close()
            for n in res.notes:
                if n != res.coreg.summary():  # the co-registration line is part of the summary below
                    sess.note(n)
            for w in res.warnings:
                sess.warn(w)
            sess.say(res.coreg.summary())
            credible = (
                ""
                if res.status != "degenerate_stable_terrain"
                else " — NOT CREDIBLE: degenerate stable terrain, see the warning"
            )
            sess.say(
                f"stable NMAD {s['stable_nmad_m']:.2f} m on {s['n_stable']} cells; changed at "
                f"{res.level:g}%: {s['changed_area_m2'] / 1e6:.4f} km², volume "
                f"{s['volume_changed_m3'] / 1e6:+.4f} ± {s['volume_changed_sigma_m3'] / 1e6:.4f} Mm³ (1σ)" + credible
            )
            sess.data(
                status=res.status,
                **{
                    k: s[k]
                    for k in (
                        "stable_nmad_m",
                        "n_stable",
                        "changed_area_m2",
                        "volume_changed_m3",
                        "volume_changed_sigma_m3",
                        "shift_applied_m",
                        "stable_identical_fraction",
                    )
                    if k in s
                },
            )
        else:
            ts = dem_time_series(
                loaded,
                base=base_ep,
                params=params,
                stable_mask=stable_mask,
                mask_is=mask_is,
                keep_arrays=pair_products,
                progress=progress,
            )
            outputs = write_timeseries_products(out_dir, ts, prefix=prefix, plots=not no_plots)
            if pair_products:
                for r in ts.intervals + ts.vs_base:
                    sub = Path(out_dir) / f"{r.epoch_a}__{r.epoch_b}"
                    pp = write_demdiff_products(sub, r, prefix=prefix, plots=not no_plots)
                    outputs.update({f"{r.epoch_a}__{r.epoch_b}_{k}": v for k, v in pp.items()})
            progress.close()
            for n in ts.notes:
                (sess.warn if "degenerate stable terrain" in n else sess.note)(n)
            iv = [r for r in ts.table if r.get("kind") == "interval" and "cumulative_net_m3" in r]
            if iv:
                last = iv[-1]
                sess.say(
                    f"{len(loaded)} DEMs, {len(ts.intervals)} intervals compared; cumulative net volume "
                    f"{iv[0]['epoch_a']} → {last['epoch_b']}: "
                    f"{last['cumulative_net_m3'] / 1e6:+.3f} ± {last.get('cumulative_net_sigma_m3', float('nan')) / 1e6:.3f}"
                    " Mm³ (1σ)"
                )
                sess.data(
                    cumulative_net_m3=last["cumulative_net_m3"],
                    cumulative_net_sigma_m3=last.get("cumulative_net_sigma_m3"),
                )
            outputs["notes"] = write_json(Path(out_dir) / f"{prefix}_notes.json", ts.notes) if ts.notes else None
            outputs = {k: v for k, v in outputs.items() if v is not None}
    finally:
        progress.close()
    emit_result(ctx, outputs)
