"""``geocd import-cameras``: frame cameras from OpenSfM/ODM or orthority files → geocd ``.camera.json`` sidecars."""

from __future__ import annotations

from pathlib import Path

import click
from .vocabulary import vertical_datum_option

_IMAGE_SUFFIXES = (".tif", ".tiff", ".jpg", ".jpeg", ".png", ".jp2")


def _image_index(folder: Path) -> dict[str, Path]:
    """Images of a folder by name and by stem (case-insensitive)."""
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in _IMAGE_SUFFIXES:
            out.setdefault(p.name.lower(), p)
            out.setdefault(p.stem.lower(), p)
    return out


@click.command("import-cameras")
@click.argument("sources", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option(
    "--image-dir",
    "images_dir",
    type=click.Path(path_type=str, file_okay=False),
    default=None,
    help="Folder of the images: each sidecar goes beside its image (IMG_0182.JPG → IMG_0182.camera.json).",
)
@click.option(
    "--out",
    "out_dir",
    type=click.Path(path_type=str, file_okay=False),
    default=None,
    help="Write the sidecars here instead (default: beside the images, else beside the source file).",
)
@click.option(
    "--crs",
    default=None,
    help="Projected CRS of the cameras: orthority x, y (default from the file's .prj "
    "or GeoJSON); for OpenSfM, the CRS to express them in (default: transverse Mercator at the reference).",
)
@vertical_datum_option(
    "Datum of the camera heights: ellipsoid, egm96 or egm2008 (orthority: required unless the CRS is compound; "
    "OpenSfM: that of its reference altitude, default ellipsoid)."
)
@click.option(
    "--reference",
    nargs=3,
    type=float,
    default=None,
    metavar="LON LAT H",
    help="OpenSfM: the topocentric origin, when reconstruction.json has no reference_lla "
    "and no reference_lla.json lies beside it.",
)
@click.option("--format", "fmt", type=click.Choice(["json", "yaml"]), default="json", show_default=True)
@click.option("--no-overwrite", is_flag=True, help="Fail instead of replacing existing sidecars.")
@click.pass_context
def import_cameras(
    ctx: click.Context,
    sources: tuple[str, ...],
    images_dir: str | None,
    out_dir: str | None,
    crs: str | None,
    vertical_datum: str | None,
    reference,
    fmt: str,
    no_overwrite: bool,
) -> None:
    """Write a geocd frame-camera sidecar for every image oriented in SOURCES.

    \b
    SOURCES is one of
      reconstruction.json                 OpenSfM / OpenDroneMap (ODM: <project>/opensfm/reconstruction.json)
      int_param.yaml ext_param.csv        orthority interior + exterior (CSV, ngi camera_pos_ori.txt or GeoJSON)

    \b
    Example (ODM project):
      geocd import-cameras odm/opensfm/reconstruction.json --image-dir odm/images
    """
    from ..errors import ConfigError, InputFileNotFoundError
    from ..io.frame import read_orthority_cameras, write_frame_sidecar
    from . import emit_result

    paths = [Path(s) for s in sources]
    for p in paths:
        if not p.is_file():
            raise InputFileNotFoundError(f"camera file {p} does not exist; check the path")
    if len(paths) == 1:
        from ..io.opensfm import read_opensfm_cameras

        cams = read_opensfm_cameras(
            paths[0], crs=crs, reference_lla=reference, vertical_datum=vertical_datum or "ellipsoid"
        )
    elif len(paths) == 2:
        cams = read_orthority_cameras(paths[0], paths[1], crs=crs, vertical_datum=vertical_datum)
    else:
        raise ConfigError(
            f"import-cameras takes one OpenSfM reconstruction.json or two orthority files "
            f"(interior, exterior), got {len(paths)} paths"
        )
    if not cams:
        raise ConfigError(f"{' + '.join(map(str, paths))} orient no image; nothing to write")
    index = {}
    if images_dir is not None:
        folder = Path(images_dir)
        if not folder.is_dir():
            raise InputFileNotFoundError(f"image folder {folder} does not exist; check --image-dir")
        index = _image_index(folder)
    default_dir = Path(out_dir) if out_dir is not None else (Path(images_dir) if images_dir else paths[-1].parent)
    outputs, missing = {}, []
    for name, cam in cams.items():
        image = index.get(name.lower()) or index.get(Path(name).stem.lower())
        if images_dir is not None and image is None:
            missing.append(name)
        target = (Path(out_dir) / Path(name).name) if out_dir is not None else (image or default_dir / Path(name).name)
        outputs[name] = write_frame_sidecar(target, cam, fmt=fmt, overwrite=not no_overwrite)
    if missing:
        click.echo(
            f"geocd: warning: {len(missing)} oriented image(s) not found in {images_dir} (sidecars written to "
            f"{default_dir}): {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}",
            err=True,
        )
    emit_result(ctx, outputs)
