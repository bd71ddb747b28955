"""What every ``geocd`` command shares: output streams, progress, the log file, defaults, units.

One :class:`Session` per command invocation (``session(ctx)``) decides where things go:

* **stdout** — what the command found and the products it wrote (``key: path`` lines), or with
  ``--json`` one JSON document (``command``, ``status``, ``outputs``, ``summary``, ``notes``,
  ``warnings``, ``log``, ``elapsed_s``). Nothing else is printed on stdout, so
  ``geocd run scene > products.txt`` keeps the product list.
* **stderr** — progress, notes (``geocd: note: ...``), warnings (``geocd: warning: ...``) and errors.
  ``--progress auto`` (default) draws a bar on a terminal and writes plain progress lines when stderr is
  a file, a pipe or a terminal of unknown or zero size (``stty cols 0``, ``COLUMNS=0``); ``bar``, ``lines``, ``json`` (the QGIS plugin's JSON-lines protocol, see
  :mod:`geocd.progress`) and ``none`` force one. A bar is closed before anything else is printed.
* **the log file** ``geocd_<command>.log`` in the command's output folder (appended, one header per run, as
  ASP and CARS keep theirs): the command line and parameters, progress, notes, warnings, the summary,
  the products, and the error (with its traceback) when the run fails.

Every command accepts ``--progress`` and ``--json`` after its name as well as before it
(:func:`add_common_options`, applied by the command group to each subcommand it loads).

Defaults: a command that writes a folder of products writes it where ``--out`` says, else in
``./geocd_out/<name>`` under the current directory (:func:`default_out_dir`) — never inside the input
folder unless asked. Inputs are checked (:func:`require_inputs`) before heavy imports so that a wrong
path fails in well under a second.

Confidence is a percentage everywhere (99 means 99 %): :func:`check_confidence` is the option
callback that rejects the 0–1 convention with a hint.
"""

from __future__ import annotations

import functools
import json
import os
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Any, Callable, Optional

import click

from ..errors import ConfigError, GeoCDError, InputFileNotFoundError, OutputError
from ..io.atomic import refuse_special_file
from ..runlog import RunLog, log_file_name
from .options import harden_options
from .vocabulary import install_legacy_names

PROGRESS_MODES = ("auto", "bar", "lines", "json", "none")
#: lowest confidence (percent) an option accepts: below it a "change" is as likely noise as not
MIN_CONFIDENCE_PCT = 50.0


# ---------------------------------------------------------------------------------------------------------------
# options every command shares
# ---------------------------------------------------------------------------------------------------------------


def dask_options(cmd: Callable) -> Callable:
    """``--scheduler``, ``--workers``, ``--memory-limit``: where a tiled run's tiles go (one wording for every command)."""
    for opt in reversed(
        (
            click.option(
                "--scheduler",
                default=None,
                metavar="SCHEDULER",
                help="Tiled runs: sync | threads | processes | auto (a local Dask cluster sized to the "
                "machine, the default; this process when there is one tile) | ADDRESS of a running "
                "dask.distributed scheduler (tcp://host:8786).",
            ),
            click.option(
                "--workers",
                type=click.IntRange(1, None),
                default=None,
                help="Tiled runs: local worker processes [one per core].",
            ),
            click.option("--memory-limit", default=None, help="Tiled runs: memory limit per local worker, e.g. 2GB."),
        )
    ):
        cmd = opt(cmd)
    return cmd


def pixel_size_option(images: str) -> Callable:
    """``--pixel-size METRES``: the ground size of a pixel of ``images`` when they have no georeference
    (:mod:`geocd.io.plain`)."""
    return click.option(
        "--pixel-size",
        "pixel_size",
        type=float,
        default=None,
        metavar="METRES",
        help=f"{images} without georeference (PNG tiles, ...): the ground size of a pixel. They are compared cell "
        "for cell on a local grid in metres (so must be one size); the products carry that local CRS.",
    )


def _progress_option() -> click.Option:
    return click.Option(
        ["--progress", "_geocd_progress"],
        type=click.Choice(PROGRESS_MODES),
        default=None,
        help="How to report progress on stderr: auto (a bar on a terminal, plain lines otherwise), "
        "bar, lines, json (JSON lines, for the QGIS plugin) or none.",
    )


def _json_option() -> click.Option:
    return click.Option(
        ["--json", "_geocd_json"],
        is_flag=True,
        default=False,
        help="Print the result (products, summary, notes) as one JSON document on stdout.",
    )


def _debug_option() -> click.Option:
    def remember(ctx: click.Context, param: click.Parameter, value: bool) -> None:
        if value:
            root = ctx.find_root()
            root.ensure_object(dict)
            root.obj["debug"] = True

    return click.Option(
        ["--debug", "_geocd_debug"],
        is_flag=True,
        default=False,
        expose_value=False,
        callback=remember,
        help="Show full tracebacks (also accepted before the command).",
    )


def add_common_options(cmd: click.Command, path: str | None = None) -> click.Command:
    """Give ``cmd`` (and, for a group, each subcommand) ``--progress``, ``--json`` and ``--debug``, the shared
    checks of numeric options (:func:`geocd.cli.options.harden_options`), its old option names
    (:mod:`geocd.cli.vocabulary`; ``path`` is the command's path without ``geocd``, default its name), and run it
    in a Session.

    Idempotent; the command group applies it to every command it loads, so a new command needs nothing
    beyond its line in ``SUBCOMMANDS``.
    """
    path = path or cmd.name or ""
    if isinstance(cmd, click.Group):
        for name, sub in cmd.commands.items():
            add_common_options(sub, f"{path} {name}")
        return cmd
    if getattr(cmd, "_geocd_common", False) or cmd.callback is None:
        return cmd
    install_legacy_names(cmd, path)
    names = {p.name for p in cmd.params}
    if "_geocd_progress" not in names:
        cmd.params.append(_progress_option())
    if "_geocd_json" not in names:
        cmd.params.append(_json_option())
    if "_geocd_debug" not in names:
        cmd.params.append(_debug_option())
    harden_options(cmd)
    cmd.callback = _in_session(cmd.callback)
    cmd._geocd_common = True  # type: ignore[attr-defined]
    return cmd


def _in_session(callback: Callable) -> Callable:
    @functools.wraps(callback)
    def run(*args, **kwargs):
        ctx = click.get_current_context()
        sess = Session.start(ctx, kwargs.pop("_geocd_progress", None), kwargs.pop("_geocd_json", False))
        try:
            refuse_special_paths(ctx.command, kwargs)
            rv = callback(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - logged, then handled by the command group
            sess.fail(exc)
            raise
        sess.finish()
        return rv

    return run


def refuse_special_paths(cmd: click.Command, values: dict) -> None:
    """Refuse a named pipe, socket or device given to any path parameter of ``cmd`` before the command runs.

    Reading a FIFO blocks until something writes into it: the command would hang instead of failing.

    Raises
    ------
    UnsupportedFormatError
    """
    for prm in cmd.params:
        if not isinstance(prm.type, click.Path) or values.get(prm.name) is None:
            continue
        v = values[prm.name]
        what = max(prm.opts, key=len) if isinstance(prm, click.Option) else "input"
        for item in v if isinstance(v, (tuple, list)) else (v,):
            if item is not None:
                refuse_special_file(item, what)


def session(ctx: click.Context | None = None) -> "Session":
    """The Session of the running command (one is started on first use if the command has none)."""
    ctx = ctx or click.get_current_context()
    root = ctx.find_root()
    root.ensure_object(dict)
    sess = root.obj.get("session")
    if sess is None:  # a command run outside the group's wrapper: finish when its context closes
        sess = Session.start(ctx, None, False)
        ctx.call_on_close(sess.finish)
    return sess


# ---------------------------------------------------------------------------------------------------------------
# inputs, outputs, units
# ---------------------------------------------------------------------------------------------------------------


def require_inputs(*paths: Optional[os.PathLike | str], what: str = "input") -> None:
    """Raise :class:`InputFileNotFoundError` for the first path that does not exist (None entries are skipped),
    :class:`~geocd.errors.UnsupportedFormatError` for a named pipe, socket or device (reading it would hang).

    Cheap (no heavy imports): call it first thing in a command.
    """
    for p in paths:
        if p is None:
            continue
        if not Path(p).exists():
            raise InputFileNotFoundError(f"{p} does not exist; check the {what} path (relative to {Path.cwd()})")
        refuse_special_file(p, what)


def default_out_dir(name: str) -> Path:
    """``./geocd_out/<name>``: where a command writes when ``--out`` is not given (current directory)."""
    from ..io.manifest import default_output_dir

    return default_output_dir(name)


def resolve_out_dir(out_dir: Optional[os.PathLike | str], name: str, *, create: bool = True) -> Path:
    """``out_dir`` or :func:`default_out_dir`; checks that it can be created and written.

    With ``create=False`` the folder is only checked (the command's output session creates it).

    Raises
    ------
    OutputError
        The folder cannot be created or written (e.g. a read-only current directory), with the fix.
    """
    explicit = out_dir is not None
    out = Path(out_dir) if explicit else default_out_dir(name)
    hint = (
        "give another --out"
        if explicit
        else f"the default output folder is under the current directory ({Path.cwd()}); give --out DIR"
    )
    if out.exists() and not out.is_dir():
        raise OutputError(f"output folder {out} is a file; {hint}")
    if create:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create the output folder {out} ({exc.strerror or exc}); {hint}") from None
    # the folder, or the nearest folder that exists above it, must be writable
    probe = out
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        what = "is not writable" if probe == out else f"cannot be created ({probe} is not a writable folder)"
        raise OutputError(f"output folder {out} {what}; {hint}")
    return out


def _pct_hint(v: float) -> str:
    return f"{100 * v:g}"


def check_confidence_value(v: float, what: str = "confidence") -> float:
    """A confidence level in percent, or :class:`ConfigError` (0–1 values get a "did you mean" hint)."""
    v = float(v)
    if 0 < v < 1:
        raise ConfigError(f"{what} is a percentage: did you mean {_pct_hint(v)}? (got {v:g}; 99 means 99 %)")
    if not MIN_CONFIDENCE_PCT <= v < 100:
        raise ConfigError(
            f"{what} {v:g} is outside [{MIN_CONFIDENCE_PCT:g}, 100): give a percentage such as 90, 95 or 99"
        )
    return v


def check_confidence(ctx: click.Context, param: click.Parameter, value):
    """click callback for options carrying a confidence (a float, or a tuple for ``multiple=True``)."""
    if value is None:
        return value
    name = f"--{param.name.replace('_', '-')}" if param.name else "confidence"
    opt = next((o for o in getattr(param, "opts", ()) if o.startswith("--")), name)
    if isinstance(value, tuple):
        return tuple(check_confidence_value(v, opt) for v in value)
    return check_confidence_value(value, opt)


# ---------------------------------------------------------------------------------------------------------------
# the session
# ---------------------------------------------------------------------------------------------------------------


class Session:
    """Streams, progress and log file of one command invocation (see the module docstring)."""

    def __init__(self, ctx: click.Context, mode: str, as_json: bool):
        self.ctx = ctx
        self.command = " ".join(ctx.command_path.split()[1:]) or ctx.command_path
        self.mode = mode
        self.as_json = as_json
        self.t0 = time.monotonic()
        self.notes: list[str] = []
        self.warnings: list[str] = []
        self.summary_lines: list[str] = []
        self.summary: dict[str, Any] = {}
        self.outputs: dict[str, str] = {}
        params = {k: v for k, v in ctx.params.items() if not k.startswith("_geocd_")}
        self._runlog = RunLog(self.command, params)
        self._bars: list = []
        self._finished = False
        #: the command printed its own result on stdout (e.g. ``info``): finish() adds nothing there
        self.stdout_done = False
        #: write a log file (commands whose output folder is published, e.g. plugin-zip, turn it off)
        self.log_enabled = True
        self._old_showwarning = None

    @property
    def log_path(self) -> Optional[Path]:
        """The log file, once opened (None before, or when it could not be written)."""
        return self._runlog.path

    @classmethod
    def start(cls, ctx: click.Context, progress: Optional[str], as_json: bool) -> "Session":
        root = ctx.find_root()
        root.ensure_object(dict)
        mode = progress or root.obj.get("progress_mode") or "auto"
        if mode == "auto":
            mode = "bar" if _isatty(sys.stderr) and _bar_fits(sys.stderr) else "lines"
        elif mode == "bar" and _isatty(sys.stderr) and not _bar_fits(sys.stderr):
            mode = "lines"  # tqdm draws nothing on a terminal of unknown or zero size
        sess = cls(ctx, mode, as_json)
        root.obj["session"] = sess
        root.obj["progress_mode"] = mode
        sess._install_warning_hook()
        return sess

    # ---- log file ---------------------------------------------------------------------------------------------
    def open_log(self, folder: os.PathLike | str) -> Optional[Path]:
        """Start writing the log into ``folder`` (created if missing); earlier lines are written first.

        Returns the log path, or None (with a warning on stderr) when the folder cannot be written.
        """
        if self._runlog.is_open or not self.log_enabled:
            return self.log_path
        try:
            return self._runlog.open(folder)
        except OSError as exc:
            path = Path(folder) / log_file_name(self.command)
            self._stderr(f"geocd: warning: cannot write the log file {path} ({exc.strerror or exc})")
            return None

    def _log_line(self, text: str) -> None:
        self._runlog.line(text)

    def log(self, text: str) -> None:
        """A line for the log file only."""
        self._runlog.lines(text)

    # ---- stderr ------------------------------------------------------------------------------------------------
    def _stderr(self, text: str) -> None:
        if self._bars:
            from tqdm import tqdm

            tqdm.write(text, file=sys.stderr)
        else:
            sys.stderr.write(text + "\n")
            sys.stderr.flush()

    def _json_event(self, obj: dict) -> None:
        sys.stderr.write(json.dumps(obj, default=str) + "\n")
        sys.stderr.flush()

    def note(self, message: str) -> None:
        """A note for the user (stderr and log), printed once however often it is given."""
        message = str(message).strip()
        if not message or message in self.notes:
            return
        self.notes.append(message)
        self._log_line(f"NOTE {message}")
        if self.mode == "json":
            self._json_event({"type": "info", "message": message})
        else:
            self._stderr(f"geocd: note: {message}")

    def warn(self, message: str) -> None:
        """A warning (stderr and log), printed once."""
        message = str(message).strip()
        if not message or message in self.warnings:
            return
        self.warnings.append(message)
        self._log_line(f"WARNING {message}")
        if self.mode == "json":
            self._json_event({"type": "warning", "message": message})
        else:
            self._stderr(f"geocd: warning: {message}")

    def _install_warning_hook(self) -> None:
        self._old_showwarning = warnings.showwarning

        def _show(message, category, filename, lineno, file=None, line=None):
            name = category.__name__
            text = str(message)
            # what the output session did (removed litter, retired a run), what a step decided (a pair left out)
            if name == "OutputFolderWarning" or getattr(category, "is_note", False):
                self.note(text)
            else:
                self.warn(text if name == "UserWarning" else f"{name}: {text}")

        warnings.showwarning = _show

    def _restore_warning_hook(self) -> None:
        if self._old_showwarning is not None:
            warnings.showwarning = self._old_showwarning
            self._old_showwarning = None

    # ---- progress ----------------------------------------------------------------------------------------------
    def progress(self, stage: str = "") -> "SessionProgress":
        """A progress callback ``(fraction, message)`` for ``stage``; call ``.close()`` when done."""
        p = SessionProgress(self, stage or self.command)
        return p

    # ---- results -----------------------------------------------------------------------------------------------
    def say(self, line: str) -> None:
        """A line of the summary (stdout when the command ends, and the log)."""
        for part in str(line).splitlines():
            self.summary_lines.append(part)

    def data(self, **items: Any) -> None:
        """Machine-readable summary entries (the ``summary`` of ``--json``)."""
        self.summary.update(items)

    def result(self, outputs: dict) -> None:
        """Record the products ({name: path}); printed when the command ends."""
        for k, v in outputs.items():
            if v is not None:
                self.outputs[str(k)] = str(v)

    def _close_bars(self) -> None:
        for b in list(self._bars):
            b.close()
        self._bars = []

    def _ensure_log_for_outputs(self) -> None:
        if self._runlog.is_open or not self.outputs:
            return
        folders = []
        for v in self.outputs.values():
            p = Path(v)
            folders.append(p if p.is_dir() else p.parent)
        try:
            common = Path(os.path.commonpath([str(f.resolve()) for f in folders]))
        except ValueError:
            return
        if common.is_dir() and os.access(common, os.W_OK) and common != Path(common.anchor):
            self.open_log(common)

    def finish(self) -> None:
        """Print the summary and products on stdout (or the JSON document), and close the log."""
        if self._finished:
            return
        self._finished = True
        self._close_bars()
        self._ensure_log_for_outputs()
        elapsed = time.monotonic() - self.t0
        for line in self.summary_lines:
            self._log_line(f"SUMMARY {line}")
        for k, v in self.outputs.items():
            self._log_line(f"OUTPUT {k}: {v}")
        self._log_line(f"done in {elapsed:.1f} s")
        if self.mode == "json" and self.outputs:
            self._json_event(
                {"type": "result", "outputs": self.outputs, **({"log": str(self.log_path)} if self.log_path else {})}
            )
        if self.stdout_done:
            pass
        elif self.as_json:
            doc = {
                "command": self.command,
                "status": "ok",
                "outputs": self.outputs,
                "summary": self.summary,
                "text": self.summary_lines,
                "notes": self.notes,
                "warnings": self.warnings,
                "log": str(self.log_path) if self.log_path else None,
                "elapsed_s": round(elapsed, 3),
            }
            click.echo(json.dumps(doc, indent=1, default=_json_default))
        else:
            for line in self.summary_lines:
                click.echo(line)
            if self.outputs:
                click.echo("products:")
                for k, v in self.outputs.items():
                    click.echo(f"  {k}: {v}")
            if self.log_path is not None:
                click.echo(f"log: {self.log_path}")
        self._close()

    def fail(self, exc: BaseException) -> None:
        """Log a failure (message, and the traceback of an unexpected error); close bars and the log."""
        if self._finished:
            return
        self._finished = True
        self._close_bars()
        if isinstance(exc, (SystemExit, click.exceptions.Exit)) and getattr(
            exc, "code", getattr(exc, "exit_code", 1)
        ) in (0, None):
            self._close()
            return
        if isinstance(exc, GeoCDError):
            self._log_line(f"ERROR {type(exc).__name__}: {exc}")
        elif isinstance(exc, KeyboardInterrupt):
            self._log_line("ERROR interrupted")
        else:
            self._log_line(f"ERROR {type(exc).__name__}: {exc}")
            self.log("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
        self._log_line(f"failed after {time.monotonic() - self.t0:.1f} s")
        keep = self._run_wrote_products()
        self._close()
        if not keep:
            self._forget_log()

    def _run_wrote_products(self) -> bool:
        """Did this run write products into the log's folder? (A failed run that wrote nothing leaves the folder
        as it was — no log either; its error is on stderr.) Unknown (no output session): yes."""
        if self.log_path is None:
            return True
        try:
            from ..io.outputs import active_sessions
        except ImportError:  # pragma: no cover
            return True
        folder = self.log_path.parent.resolve()
        mine = [
            s
            for s in active_sessions()
            if (s.folder is not None and s.folder.resolve() == folder)
            or any(Path(f).resolve().parent == folder for f in s.files)
        ]
        return not mine or any(s.written for s in mine)

    def _forget_log(self) -> None:
        self._runlog.forget()

    def _close(self) -> None:
        self._restore_warning_hook()
        self._runlog.close()
        root = self.ctx.find_root()
        if root.obj and root.obj.get("session") is self:
            root.obj["session"] = None


def _json_default(o):
    if isinstance(o, Path):
        return str(o)
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(o)


def _isatty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


#: smallest terminal a progress bar is drawn on (columns, lines); smaller or unknown gets plain lines
MIN_BAR_SIZE = (20, 3)


def _bar_fits(stream) -> bool:
    """True when the terminal of ``stream`` reports a size a tqdm bar can be drawn in.

    A terminal that reports 0 columns (``stty cols 0``, a pty of size 0x0) or whose size cannot be read, and
    ``COLUMNS=0`` in the environment, get plain progress lines: tqdm would hide its bar there and the run would
    print nothing.
    """
    env = os.environ.get("COLUMNS", "").strip()
    if env:
        try:
            if int(env) < MIN_BAR_SIZE[0]:
                return False
        except ValueError:
            pass
    try:
        size = os.get_terminal_size(stream.fileno())
    except (AttributeError, ValueError, OSError):
        return False
    return size.columns >= MIN_BAR_SIZE[0] and size.lines >= MIN_BAR_SIZE[1]


class SessionProgress:
    """A progress callback of a :class:`Session`: bar, plain lines, JSON lines or nothing, and the log.

    Plain lines (and the log) get one line per 5 % step or every 30 s, whichever comes first, and the last one.
    """

    STEP = 0.05
    MAX_SILENCE_S = 30.0

    def __init__(self, sess: Session, stage: str):
        self.sess = sess
        self.stage = stage
        self.mode = sess.mode
        self._last_step = -1
        self._last_t = 0.0
        self._fraction: Optional[float] = None
        self._closed = False
        self._bar = None
        self._json = None
        if self.mode == "bar":
            from ..progress import TqdmProgress

            self._bar = TqdmProgress(desc=stage, disable=False)
            sess._bars.append(self)
        elif self.mode == "json":
            from ..progress import JSONLinesProgress

            self._json = JSONLinesProgress(stage=stage)

    def __call__(self, fraction: Optional[float], message: str = "") -> None:
        if self._closed:
            return
        if self._bar is not None:
            self._bar(fraction, message)
        elif self._json is not None:
            self._json(fraction, message)
        now = time.monotonic()
        if fraction is not None:
            self._fraction = fraction
        step = int((fraction or 0.0) / self.STEP + 1e-9) if fraction is not None else self._last_step
        if step > self._last_step or now - self._last_t >= self.MAX_SILENCE_S or (fraction or 0) >= 1.0:
            if (fraction or 0) >= 1.0 and self._last_step >= int(1 / self.STEP):
                return
            self._last_step = max(step, self._last_step)
            self._last_t = now
            pct = "   " if fraction is None else f"{100 * fraction:3.0f}%"
            line = f"{self.stage} {pct} {message}".rstrip()
            self.sess._log_line(f"PROGRESS {line}")
            if self.mode == "lines":
                elapsed = now - self.sess.t0
                sys.stderr.write(f"geocd: [{elapsed:6.1f} s] {line}\n")
                sys.stderr.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()
            if self in self.sess._bars:
                self.sess._bars.remove(self)
