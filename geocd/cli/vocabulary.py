"""One option vocabulary for every command, and the old option names still accepted.

Every command spells a concept the same way (``tests/cli/test_vocabulary.py`` reads every command's options and
holds them to this table):

==========================  =========================================================================
option                      meaning, in every command that has it
==========================  =========================================================================
``--out``                   where the products go; never required, default ``./geocd_out/<name>``
                            (a command writing one file puts it in that folder)
``--epoch-a/--epoch-b``     an epoch of the manifest, by name
``--epoch``                 epochs of the manifest to use, by name (repeatable)
``--image``                 images to use, by manifest name or file (repeatable)
``--image-a/--image-b``     the image(s) of epoch A / B, by manifest name (with a manifest) or file
``--pair-dem-a/-b``         pair-DEM GeoTIFFs of epoch A / B (repeatable)
``--vertical-datum``        the vertical datum of DEMs whose file does not say it
``--posting``               the grid posting in metres
``--scheduler``             sync | threads | processes | auto (the default) | a Dask address
``--confidence``            confidence levels in percent
``--footprints``            a building-footprint vector file
``--model``                 a model file to reuse
==========================  =========================================================================

Options renamed to fit it keep working under their old names for scripts written before: the command line is
rewritten before click parses it (:func:`rewrite_legacy`) and a note names the new spelling. The old names are
not shown in ``--help``.
"""

from __future__ import annotations

from typing import Callable, Sequence

import click

#: command path (without ``geocd``) → {old option name: new option name}
LEGACY: dict[str, dict[str, str]] = {
    "change": {
        "-a": "--pair-dem-a",
        "--epoch-a": "--pair-dem-a",
        "-b": "--pair-dem-b",
        "--epoch-b": "--pair-dem-b",
        "--dem-vertical-datum": "--vertical-datum",
    },
    "landcover integrate": {"--dem-datum": "--vertical-datum"},
    "landcover predict": {"--dem-datum": "--vertical-datum"},
    "landcover train": {"--dem-datum": "--vertical-datum"},
    "synth": {"--posting-m": "--posting", "--size-m": "--size", "--gsd-m": "--gsd"},
    "probchange": {"--images-a": "--image-a", "--images-b": "--image-b", "--model": "--formulation"},
    "mpp": {"--view-a": "--image-a", "--view-b": "--image-b"},
    "screen": {"--pair": "--image-a --image-b"},
    "volume update": {"--footprints": "--roofs-from-footprints"},
    "import-cameras": {"--images": "--image-dir"},
}

#: options whose old spelling took comma-separated values where the new one is repeated
_SPLIT_COMMAS = {("probchange", "--images-a"), ("probchange", "--images-b")}


def rewrite_legacy(path: str, args: Sequence[str], note: Callable[[str], None] | None = None) -> list[str]:
    """``args`` with the old option names of command ``path`` replaced by the new ones.

    ``--old VALUE``, ``--old=VALUE`` and flags are handled; an old name mapped to two new ones (``--pair A B`` →
    ``--image-a A --image-b B``) takes one value for each. Arguments after ``--`` are left alone.

    Parameters
    ----------
    path : the command's path without ``geocd`` (``"landcover train"``)
    args : the command's arguments as given
    note : called once per old name used, with a sentence naming the new one
    """
    table = LEGACY.get(path)
    if not table:
        return list(args)
    out: list[str] = []
    said: set[str] = set()
    i = 0
    args = list(args)
    while i < len(args):
        a = args[i]
        if a == "--":
            out.extend(args[i:])
            break
        name, eq, value = a.partition("=") if a.startswith("--") else (a, "", "")
        new = table.get(name)
        if new is None:
            out.append(a)
            i += 1
            continue
        if note is not None and name not in said:
            said.add(name)
            note(f"{name} is now spelled {new}; the old name still works but will be removed in a later version")
        targets = new.split()
        if len(targets) == 1:
            vals = [value] if eq else []
            if (path, name) in _SPLIT_COMMAS:
                if not eq and i + 1 < len(args):
                    vals, i = [args[i + 1]], i + 1
                for v in ",".join(vals).split(","):
                    if v.strip():
                        out += [targets[0], v.strip()]
            else:
                out.append(f"{targets[0]}={value}" if eq else targets[0])
            i += 1
            continue
        # one old option holding one value for each of several new ones
        vals = args[i + 1 : i + 1 + len(targets)]
        for t, v in zip(targets, vals):
            out += [t, v]
        i += 1 + len(vals)
    return out


def install_legacy_names(cmd: click.Command, path: str) -> None:
    """Make ``cmd`` accept the old option names of :data:`LEGACY` (idempotent)."""
    if path not in LEGACY or getattr(cmd, "_geocd_legacy", False):
        return
    parse = cmd.parse_args

    def parse_args(ctx: click.Context, args: list[str]) -> list[str]:
        return parse(ctx, rewrite_legacy(path, args, note=lambda m: click.echo(f"geocd: note: {m}", err=True)))

    cmd.parse_args = parse_args  # type: ignore[method-assign]
    cmd._geocd_legacy = True  # type: ignore[attr-defined]


def _check_datum(ctx: click.Context, param: click.Parameter, value):
    from ..errors import VerticalDatumError
    from ..io.raster import check_vertical_datum

    def one(v):  # "file": what the DEM's own file says (a placeholder when giving A's and B's in turn)
        return None if v is not None and str(v).strip().lower() == "file" else check_vertical_datum(v)

    try:
        if isinstance(value, tuple):
            return tuple(one(v) for v in value)
        return one(value)
    except VerticalDatumError as exc:
        raise click.BadParameter(str(exc).split(": ", 1)[-1], ctx=ctx, param=param) from None


def vertical_datum_option(help: str, *, dest: str = "vertical_datum", multiple: bool = False) -> Callable:
    """``--vertical-datum``: ellipsoid, egm96 or egm2008 (and their aliases), or ``file`` (what the DEM's file
    says), checked when parsed."""
    return click.option(
        "--vertical-datum",
        dest,
        default=None,
        multiple=multiple,
        metavar="DATUM",
        callback=_check_datum,
        help=help,
    )
