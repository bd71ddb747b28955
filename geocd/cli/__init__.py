"""The ``geocd`` command line.

Subcommands live in their own modules and are loaded lazily (fast start-up,
and the plugin's child processes pay only for what they run). To add one, add a
line to :data:`SUBCOMMANDS`: ``"name": "geocd.cli.module:function"``.

Every command shares ``--progress {bar,json,none}``; ``json`` is the QGIS
plugin's protocol (see :mod:`geocd.progress`).

One error path (:meth:`LazyGroup.invoke`): a :class:`~geocd.errors.GeoCDError` is
printed as one line (``geocd: error: ...``) and exits with its ``exit_code`` (2)
without a traceback; any other exception is first turned into the GeoCDError that
stands for it (:func:`geocd.faults.translate`: out of memory, disk full, read-only
file system, a corrupt file, ... or "internal error" for a bug); ``--debug`` shows
the traceback. Ctrl-C, SIGTERM and SIGHUP clean up the same way (partial files
removed, the output session recorded as interrupted) and exit 128 + signal
(130, 143, 129). Output sessions opened by a command
(:func:`geocd.io.outputs.open_outputs`) are closed here when it ends.
"""

from __future__ import annotations

import importlib
import json
import sys
import warnings

import click

from .. import __version__

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
}


class LazyGroup(click.Group):
    def parse_args(self, ctx, args):
        ctx.meta["geocd.argv"] = ["geocd", *args]  # the command line, recorded with the products it writes
        return super().parse_args(ctx, args)

    def list_commands(self, ctx):
        return sorted(SUBCOMMANDS)

    def get_command(self, ctx, name):
        target = SUBCOMMANDS.get(name)
        if target is None:
            return None
        mod, attr = target.split(":")
        return getattr(importlib.import_module(mod), attr)

    def invoke(self, ctx):
        from ..faults import exit_code_for_interrupt, one_line, signal_name, signals_as_interrupts, translate
        from ..io.outputs import OutputFolderWarning, close_sessions

        debug = ctx.params.get("debug", False)
        mode = ctx.params.get("progress", "bar")

        def report(kind: str, message: str) -> None:
            if mode == "json":
                sys.stderr.write(json.dumps({"type": "error", "error": kind, "message": message}) + "\n")
            click.echo(f"geocd: error: {message}", err=True)

        with warnings.catch_warnings():
            warnings.simplefilter("always", OutputFolderWarning)
            shown = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):
                if issubclass(category, OutputFolderWarning) and mode != "json":
                    click.echo(f"geocd: note: {message}", err=True)
                else:
                    shown(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            try:
                with signals_as_interrupts():
                    rv = super().invoke(ctx)
                    close_sessions(ok=True)
                return rv
            except (click.exceptions.Exit, click.exceptions.Abort, click.exceptions.ClickException) as exc:
                close_sessions(ok=isinstance(exc, click.exceptions.Exit) and exc.exit_code == 0, exc=exc)
                raise
            except KeyboardInterrupt as exc:
                close_sessions(ok=False, exc=exc)
                if debug:
                    raise
                what = ("interrupted (Ctrl-C)" if type(exc) is KeyboardInterrupt
                        else f"stopped by {signal_name(exc.signum)}")
                report("CancelledError", f"{what}; partial files were removed and the products already written are "
                                         "listed as interrupted in the output folder's geocd_products.json; run the "
                                         "command again to complete them")
                ctx.exit(exit_code_for_interrupt(exc))
            except Exception as exc:  # noqa: BLE001 - the single error path: everything becomes a GeoCDError
                close_sessions(ok=False, exc=exc)
                if debug:
                    raise
                err = translate(exc)
                report(type(err).__name__, one_line(err))
                ctx.exit(getattr(err, "exit_code", 2))


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
