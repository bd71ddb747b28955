"""``geocd synth``: generate a synthetic scene folder with known truth (what ``sample_aoi/`` is)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from . import emit_result, make_progress


@click.command("synth")
@click.option(
    "--out",
    "out_dir",
    default=None,
    type=click.Path(file_okay=False, path_type=Path),
    help="Folder to write (must be empty unless --overwrite; default: ./geocd_out/<scene name>).",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (0 reproduces sample_aoi/).")
@click.option("--size", "size_m", type=float, default=300.0, show_default=True, help="Side of the square AOI, metres.")
@click.option(
    "--gsd", "gsd_m", type=float, default=0.5, show_default=True, help="Satellite ground sampling distance, metres."
)
@click.option(
    "--posting", "posting_m", type=float, default=0.5, show_default=True, help="Truth/AOI grid posting, metres."
)
@click.option("--n-sat-a", type=int, default=4, show_default=True, help="Satellite views of epoch A.")
@click.option("--n-sat-b", type=int, default=3, show_default=True, help="Satellite views of epoch B.")
@click.option("--n-aerial", type=int, default=3, show_default=True, help="Aerial RGB frames of epoch A.")
@click.option(
    "--changes",
    type=str,
    default=None,
    help="Comma-separated change types to enable (default all): new, demolished, raised, lowered, cars, "
    "trees, repaint, season.",
)
@click.option("--same-sun", is_flag=True, help="Render epoch B under epoch A's sun (illumination control).")
@click.option("--supersample", type=int, default=2, show_default=True, help="k: k x k rays per pixel.")
@click.option("--tiny", is_flag=True, help="Preset: 64 m scene, 2+2 satellite views, 2 frames (for tests).")
@click.option("--name", type=str, default=None, help="Scene name written into scene.yaml.")
@click.option(
    "--params",
    "params_file",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="JSON with SynthParams fields (e.g. the 'params' of a scene's truth/scene_truth.json); "
    "options given on the command line override it.",
)
@click.option(
    "--pictures",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Also write PNG quick-looks (images, DSMs, change mask) into this folder.",
)
@click.option("--overwrite", is_flag=True, help="Replace the files of an existing scene folder.")
@click.pass_context
def synth(
    ctx: click.Context,
    out_dir: Path | None,
    seed: int,
    size_m: float,
    gsd_m: float,
    posting_m: float,
    n_sat_a: int,
    n_sat_b: int,
    n_aerial: int,
    changes: str | None,
    same_sun: bool,
    supersample: int,
    tiny: bool,
    name: str | None,
    params_file: Path | None,
    pictures: Path | None,
    overwrite: bool,
) -> None:
    """Generate a synthetic town with two epochs, satellite (RPC) and aerial (frame) views, and exact truth.

    The result is a scene folder (scene.yaml + images + truth) that every geocd command accepts. With the
    defaults, `geocd synth` regenerates the committed sample_aoi/ (same pixels and truth on the same
    platform; see truth/scene_truth.json for the recorded parameters and checks).
    """
    from ..errors import ConfigError
    from ..io.outputs import open_outputs
    from ..synth.generate import SynthParams, generate

    base: dict = {}
    if params_file is not None:
        try:
            base = json.loads(params_file.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(
                f"{params_file} is not valid JSON text ({exc}); give a JSON of SynthParams fields"
            ) from exc
        if not isinstance(base, dict):
            raise ConfigError(f"{params_file} holds a JSON {type(base).__name__}, not SynthParams fields")
        if "params" in base and isinstance(base["params"], dict):
            base = base["params"]
    given = {
        k: v for k, v in ctx.params.items() if ctx.get_parameter_source(k) == click.core.ParameterSource.COMMANDLINE
    }
    opts = {
        "seed": seed,
        "size_m": size_m,
        "gsd_m": gsd_m,
        "posting_m": posting_m,
        "n_sat_a": n_sat_a,
        "n_sat_b": n_sat_b,
        "n_aerial": n_aerial,
        "same_sun": same_sun,
        "supersample": supersample,
    }
    kw = dict(base)
    for k, v in opts.items():
        if k in given or k not in kw:
            kw[k] = v
    if changes is not None:
        kw["changes"] = tuple(c.strip() for c in changes.split(",") if c.strip())
    if name is not None:
        kw["name"] = name
    if tiny:
        tiny_defaults = SynthParams.tiny().to_dict()
        for k in (
            "size_m",
            "n_sat_a",
            "n_sat_b",
            "n_aerial",
            "n_buildings",
            "n_new",
            "n_demolished",
            "n_raised",
            "n_lowered",
            "n_cars_moved",
            "n_trees_changed",
            "n_repainted",
            "name",
        ):
            if k not in given and not (k == "name" and name is not None):
                kw[k] = tiny_defaults[k]
    params = SynthParams.from_dict(kw)  # every value checked before the output folder is touched
    if out_dir is None:
        from .common import resolve_out_dir

        out_dir = resolve_out_dir(None, params.name or "synth", create=False)
    open_outputs(out_dir, inputs=[params_file], files=[pictures])
    prog = make_progress(ctx, "synth")
    try:
        res = generate(params, out_dir, overwrite=overwrite, progress=prog)
    finally:
        prog.close()
    from .common import session

    sess = session(ctx)
    sess.open_log(out_dir)  # after generating: the generator wants an empty folder
    rep = res.report
    n_views = len(rep.get("views", []))
    sess.say(
        f"scene {params.name!r} (seed {params.seed}): {n_views} views, "
        f"{100 * rep.get('change_mask_fraction', 0.0):.2f}% of the AOI changed in 3-D"
    )
    sess.data(seed=params.seed, views=n_views, change_mask_fraction=rep.get("change_mask_fraction"))
    outputs = {"manifest": res.manifest, "report": out_dir / "truth" / "scene_truth.json"}
    if pictures is not None:
        from ..synth.pictures import write_pictures

        for k, p in write_pictures(out_dir, pictures, prefix=f"{params.name}_").items():
            outputs[f"picture_{k}"] = p
    emit_result(ctx, outputs)
