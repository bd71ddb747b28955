"""The ``geocd`` command line.

Subcommands live in their own modules and are loaded lazily (fast start-up,
and the plugin's child processes pay only for what they run). To add one, add a
line to :data:`SUBCOMMANDS`: ``"name": "geocd.cli.module:function"``.

Conventions every command follows (implemented once in :mod:`geocd.cli.common`;
a new command gets them by being listed in :data:`SUBCOMMANDS`):

* ``--progress {auto,bar,lines,json,none}`` and ``--json`` are accepted before or after
  the command name. Progress, notes and warnings go to stderr (a bar on a terminal, plain
  lines otherwise; ``json`` is the QGIS plugin's protocol, see :mod:`geocd.progress`).
* stdout carries only the result: summary lines and ``products:`` (``key: path``), or one
  JSON document with ``--json``.
* A command that writes products keeps a log file ``geocd_<command>.log`` in its output
  folder (``session(ctx).open_log(out)``; otherwise the folder of its products).
* ``--out`` defaults to ``./geocd_out/<name>`` in the current directory
  (``resolve_out_dir``), never the input folder. Inputs are checked before heavy
  imports (``require_inputs``).
* Confidence is a percentage (99 = 99 %) in every option, raster band, layer field,
  QGIS parameter and JSON file; options carrying one use ``callback=check_confidence``,
  which rejects 0–1 values ("did you mean 95?").
* Inside a command: ``p = make_progress(ctx, stage)`` (call ``p.close()``),
  ``session(ctx).note(...)`` / ``.say(...)`` / ``.data(...)``, and
  ``emit_result(ctx, {name: path})`` for the products.

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

import contextlib
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
    "plugin-install": "geocd.cli.plugin:plugin_install",
    "synth": "geocd.cli.synth:synth",
    "volume": "geocd.cli.volume:volume",
    "run": "geocd.cli.change:run",
    "consistency": "geocd.cli.change:consistency",
    "change": "geocd.cli.change:change",
    "stereo": "geocd.cli.stereo:stereo",
    "probchange": "geocd.cli.probchange:probchange",
    "ortho": "geocd.cli.ortho:ortho",
    "mpp": "geocd.cli.mpp:mpp",
    "landcover": "geocd.cli.landcover:landcover",
    "screen": "geocd.cli.screen:screen",
    "import-cameras": "geocd.cli.import_cameras:import_cameras",
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
        from .common import add_common_options

        return add_common_options(getattr(importlib.import_module(mod), attr))

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except click.exceptions.UsageError as exc:  # an option of geocd itself (before the command name)
            _usage_error(exc)

    def invoke(self, ctx):
        from ..faults import exit_code_for_interrupt, one_line, signal_name, signals_as_interrupts, translate
        from ..io.outputs import OutputFolderWarning, close_sessions

        def debug() -> bool:  # --debug before the command, or after it (read when an error comes)
            return bool(ctx.params.get("debug") or (ctx.obj or {}).get("debug"))

        mode = (ctx.obj or {}).get("progress_mode") or ctx.params.get("progress")
        from .._jit import install_compile_notice

        install_compile_notice(json_lines=mode == "json")

        def report(kind: str, message: str) -> None:
            if mode == "json":
                sys.stderr.write(json.dumps({"type": "error", "error": kind, "message": message}) + "\n")
            click.echo(f"geocd: error: {message}", err=True)

        prev_hook = sys.unraisablehook
        with warnings.catch_warnings(), _restore_unraisablehook(prev_hook):
            warnings.simplefilter("always", OutputFolderWarning)
            shown = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):
                if issubclass(category, OutputFolderWarning) and mode != "json":
                    click.echo(f"geocd: note: {message}", err=True)
                else:
                    shown(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            if not debug():
                # an exception inside a library callback (rasterio's GDAL log handler failing to decode a corrupt
                # file's message) is printed by Python as a traceback although nothing failed: keep stderr clean
                sys.unraisablehook = lambda u: None
            try:
                with signals_as_interrupts():
                    rv = super().invoke(ctx)
                    close_sessions(ok=True)
                return rv
            except click.exceptions.UsageError as exc:
                close_sessions(ok=False, exc=exc)
                _usage_error(exc, json_lines=mode == "json")
            except (click.exceptions.Exit, click.exceptions.Abort, click.exceptions.ClickException) as exc:
                close_sessions(ok=isinstance(exc, click.exceptions.Exit) and exc.exit_code == 0, exc=exc)
                raise
            except KeyboardInterrupt as exc:
                close_sessions(ok=False, exc=exc)
                if debug():
                    raise
                what = (
                    "interrupted (Ctrl-C)"
                    if type(exc) is KeyboardInterrupt
                    else f"stopped by {signal_name(exc.signum)}"
                )
                report(
                    "CancelledError",
                    f"{what}; partial files were removed and the products already written are "
                    "listed as interrupted in the output folder's geocd_products.json; run the "
                    "command again to complete them",
                )
                ctx.exit(exit_code_for_interrupt(exc))
            except Exception as exc:  # noqa: BLE001 - the single error path: everything becomes a GeoCDError
                close_sessions(ok=False, exc=exc)
                if debug():
                    raise
                err = translate(exc)
                report(type(err).__name__, one_line(err))
                ctx.exit(getattr(err, "exit_code", 2))


def _usage_error(exc: click.exceptions.UsageError, json_lines: bool = False) -> None:
    """A wrong command line: one ``geocd: error:`` line naming the problem and where help is, exit 2."""
    message = exc.format_message().rstrip(".")
    where = " ".join(["geocd", *exc.ctx.command_path.split()[1:]]) if exc.ctx is not None else "geocd"
    message = f"{message[:1].lower()}{message[1:]} (see '{where} --help')"
    if json_lines:
        sys.stderr.write(json.dumps({"type": "error", "error": "UsageError", "message": message}) + "\n")
    click.echo(f"geocd: error: {message}", err=True)
    raise click.exceptions.Exit(exc.exit_code)


@contextlib.contextmanager
def _restore_unraisablehook(hook):
    try:
        yield
    finally:
        sys.unraisablehook = hook


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="geocd")
@click.option(
    "--progress",
    type=click.Choice(["auto", "bar", "lines", "json", "none"]),
    default="auto",
    show_default=True,
    help="How to report progress on stderr: auto (a bar on a terminal, plain lines otherwise), bar, "
    "lines, json (JSON lines, for the QGIS plugin) or none. Also accepted after the command.",
)
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
    """The progress callback that matches ``--progress`` (call ``.close()`` when done); also feeds the log."""
    from .common import session

    return session(ctx).progress(stage)


def emit_result(ctx: click.Context, outputs: dict) -> None:
    """Record the products ({name: path}): printed on stdout (and as the plugin's result line) when the command ends."""
    from .common import session

    session(ctx).result(outputs)


if __name__ == "__main__":  # pragma: no cover
    main()
