"""The ``geocd`` command line.

Subcommands live in their own modules and are loaded lazily (fast start-up,
and the plugin's child processes pay only for what they run). To add one, add a
line to :data:`SUBCOMMANDS`: ``"name": "geocd.cli.module:function"``.

Every command shares ``--progress {bar,json,none}``; ``json`` is the QGIS
plugin's protocol (see :mod:`geocd.progress`). A :class:`~geocd.errors.GeoCDError`
is printed as one line (``geocd: error: ...``) and exits non-zero without a
traceback; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import importlib
import json
import sys
import warnings

import click

from .. import __version__
from ..errors import GeoCDError

SUBCOMMANDS: dict[str, str] = {
    "info": "geocd.cli.info:info",
    "demdiff": "geocd.cli.demdiff:demdiff",
    "plugin-zip": "geocd.cli.plugin:plugin_zip",
    "synth": "geocd.cli.synth:synth",
    "volume": "geocd.cli.volume:volume",
    "run": "geocd.cli.change:run",
    "consistency": "geocd.cli.change:consistency",
    "change": "geocd.cli.change:change",
    "stereo": "geocd.cli.stereo:stereo",
    "probchange": "geocd.cli.probchange:probchange",
    "import-cameras": "geocd.cli.import_cameras:import_cameras",
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return sorted(SUBCOMMANDS)

    def get_command(self, ctx, name):
        target = SUBCOMMANDS.get(name)
        if target is None:
            return None
        mod, attr = target.split(":")
        return getattr(importlib.import_module(mod), attr)

    def invoke(self, ctx):
        debug = ctx.params.get("debug", False)
        mode = ctx.params.get("progress", "bar")
        from .._jit import install_compile_notice
        install_compile_notice(json_lines=mode == "json")
        try:
            return super().invoke(ctx)
        except GeoCDError as exc:
            if debug:
                raise
            if mode == "json":
                sys.stderr.write(json.dumps({"type": "error", "error": type(exc).__name__, "message": str(exc)}) + "\n")
            click.echo(f"geocd: error: {exc}", err=True)
            ctx.exit(getattr(exc, "exit_code", 2))


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="geocd")
@click.option("--progress", type=click.Choice(["bar", "json", "none"]), default="bar", show_default=True,
              help="How to report progress: a bar, JSON lines on stderr (for the QGIS plugin), or nothing.")
@click.option("--debug", is_flag=True, help="Show full tracebacks.")
@click.pass_context
def main(ctx: click.Context, progress: str, debug: bool) -> None:
    """geocd: find where the 3-D shape of the world changed, and how sure we are."""
    ctx.ensure_object(dict)
    ctx.obj["progress_mode"] = progress
    ctx.obj["debug"] = debug
    if progress == "json":
        _route_warnings_to_json()


def _route_warnings_to_json() -> None:
    def _show(message, category, filename, lineno, file=None, line=None):
        sys.stderr.write(json.dumps({"type": "warning", "message": f"{category.__name__}: {message}"}) + "\n")

    warnings.showwarning = _show


def make_progress(ctx: click.Context, stage: str):
    """The progress callback that matches ``--progress`` (call ``.close()`` if present when done)."""
    from ..progress import JSONLinesProgress, TqdmProgress, null_progress

    mode = (ctx.find_root().obj or {}).get("progress_mode", "bar")
    if mode == "json":
        return JSONLinesProgress(stage=stage)
    if mode == "none":
        return null_progress
    return TqdmProgress(desc=stage, disable=not sys.stderr.isatty())


def emit_result(ctx: click.Context, outputs: dict) -> None:
    """Announce output files (JSON line for the plugin, a summary otherwise)."""
    mode = (ctx.find_root().obj or {}).get("progress_mode", "bar")
    if mode == "json":
        sys.stderr.write(json.dumps({"type": "result", "outputs": {k: str(v) for k, v in outputs.items()}}) + "\n")
    else:
        for k, v in outputs.items():
            click.echo(f"{k}: {v}", err=True)


if __name__ == "__main__":  # pragma: no cover
    main()
