"""``geocd probchange MANIFEST``: probability of 3-D change without reconstruction (Sakurada's thesis, ch. 5)."""

from __future__ import annotations

import click


@click.command("probchange")
@click.argument("manifest", type=click.Path(path_type=str))
@click.option(
    "--variant",
    type=click.Choice(["objectspace", "keyframe"]),
    default="objectspace",
    show_default=True,
    help="objectspace: vertical rays on the AOI grid (satellites); keyframe: rays of a key frame's pixels.",
)
@click.option(
    "--key", default=None, help="Key-frame image name (keyframe variant; default: the first image of epoch A)."
)
@click.option("--epoch-a", default=None, help="First epoch (default: the earliest).")
@click.option("--epoch-b", default=None, help="Second epoch (default: the latest).")
@click.option(
    "--image-a", "images_a", multiple=True, help="An image of epoch A to use, by name (repeatable; default: all)."
)
@click.option(
    "--image-b", "images_b", multiple=True, help="An image of epoch B to use, by name (repeatable; default: all)."
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str),
    default=None,
    help="Output folder (default: the manifest's 'output:' if it names one, else ./geocd_out/<scene name>).",
)
@click.option(
    "--formulation",
    "model",
    type=click.Choice(["robust", "thesis"]),
    default="robust",
    show_default=True,
    help="thesis: eqs. 5.2-5.11 as published; robust: + 'no consistent depth' hypothesis, visibility test, "
    "all pairs (see docs/probchange.md).",
)
@click.option("--prior", "prior_change", type=float, default=None, help="Prior p(c=1) (default 0.5).")
@click.option("--bins", "n_bins", type=int, default=None, help="Hypotheses per ray (default 128).")
@click.option(
    "--sigma", type=float, default=None, help="σ of the depth epoch (0-255 scale; default: estimated, §5.3.5)."
)
@click.option("--sigma-prime", type=float, default=None, help="σ' of the other epoch (default: estimated).")
@click.option(
    "--threshold",
    type=float,
    default=None,
    help="Binary change where the change probability p > threshold (a probability 0–1, not a confidence; default 0.5).",
)
@click.option(
    "--pairs",
    type=click.Choice(["star", "consecutive", "all"]),
    default=None,
    help="Pairs within an epoch (default: star for thesis, all for robust).",
)
@click.option("--symmetric/--no-symmetric", default=None, help="Also swap the epochs and combine (default: no).")
@click.option(
    "--height-range",
    nargs=2,
    type=float,
    default=None,
    metavar="MIN MAX",
    help="Ellipsoidal height range of the hypotheses, metres (default: prior DEM − 5 / + 40 m, else cameras).",
)
@click.option(
    "--posting", "posting_m", type=float, default=None, help="Grid posting in metres (default: manifest aoi)."
)
@click.option("--prefix", default=None, help="File name prefix of the products (default probchange).")
@click.pass_context
def probchange(
    ctx: click.Context,
    manifest: str,
    variant: str,
    key: str | None,
    epoch_a: str | None,
    epoch_b: str | None,
    images_a: tuple[str, ...],
    images_b: tuple[str, ...],
    out_dir: str | None,
    model: str,
    prior_change: float | None,
    n_bins: int | None,
    sigma: float | None,
    sigma_prime: float | None,
    threshold: float | None,
    pairs: str | None,
    symmetric: bool | None,
    height_range,
    posting_m: float | None,
    prefix: str | None,
) -> None:
    """Probability that the 3-D structure changed between two epochs of MANIFEST, never deciding the depth.

    Patches are compared only within an epoch (5x5 mean absolute differences), so a different sun or sensor
    between the epochs does not raise false alarms. Writes the change probability on the AOI grid (and in the
    key frame's geometry), the binary change at p > 0.5 and its polygons (GeoPackage layer 'changes',
    method 'probchange').
    """
    from .common import require_inputs, resolve_out_dir, session

    require_inputs(manifest, what="manifest")
    from ..io.manifest import load_manifest
    from ..io.outputs import open_outputs

    m = load_manifest(manifest)
    out = resolve_out_dir(out_dir if out_dir is not None else m.output, m.name, create=False)
    from ..probchange import ProbChangeParams
    from ..probchange.pipeline import run_probchange
    from . import emit_result, make_progress

    open_outputs(out, inputs=m.input_paths(), products=(f"{prefix or 'probchange'}_*",), prefix=prefix)
    sess = session(ctx)
    sess.open_log(out)
    kw: dict = {}
    for name, val in (
        ("prior_change", prior_change),
        ("n_bins", n_bins),
        ("sigma", sigma),
        ("sigma_prime", sigma_prime),
        ("threshold", threshold),
        ("pairs", pairs),
        ("symmetric", symmetric),
    ):
        if val is not None:
            kw[name] = val
    if height_range:
        kw["height_range_m"] = tuple(height_range)
    params = ProbChangeParams.robust(**kw) if model == "robust" else ProbChangeParams(**kw)
    progress = make_progress(ctx, "probchange")
    try:
        res = run_probchange(
            m,
            variant=variant,
            key=key,
            epoch_a=epoch_a,
            epoch_b=epoch_b,
            images_a=list(images_a) or None,
            images_b=list(images_b) or None,
            out_dir=out,
            params=params,
            posting_m=posting_m,
            prefix=prefix,
            progress=progress,
        )
    finally:
        progress.close()
    s = res["summary"]
    sess.say(
        f"probchange ({variant}) {s['epoch_a']} → {s['epoch_b']}: observed {100 * s['observed_fraction']:.1f}% of "
        f"cells; changed (p > {params.threshold:g}): {100 * s['changed_fraction']:.2f}%"
    )
    sess.data(**{k: s[k] for k in ("epoch_a", "epoch_b", "observed_fraction", "changed_fraction") if k in s})
    emit_result(ctx, res["outputs"])
