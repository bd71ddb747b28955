"""Checks every command's numeric options share: finite numbers, and the ranges that options of one name mean.

click converts ``--posting 0``, ``--threshold nan`` or ``--seed -1`` without a word, and a value out of range then
fails deep inside a method ("internal error"), or worse, is clamped and a result written with exit 0. Here every
option of every command is checked once, when it is parsed and before any work:

* every float option (and each number of a multi-number option such as ``--bounds``) must be finite;
* an option named in :data:`RULES` must also lie in that option's range, with the same meaning and message in
  every command that has it (``--posting`` is a positive grid posting in metres wherever it appears).

:func:`harden_options` is applied by the command group to each command it loads
(:func:`geocd.cli.common.add_common_options`), so a new command is covered with no edit here; a new option name
that needs a range gets one line in :data:`RULES`. A refusal is a :class:`click.BadParameter`, printed as one
``geocd: error:`` line with exit 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Optional

import click


@dataclass(frozen=True)
class Rule:
    """The range of one option name: ``low``/``high`` bounds (None: open-ended), whether they are excluded,
    and what the value is, for the message (``"a grid posting in metres"``)."""

    what: str
    low: Optional[float] = None
    high: Optional[float] = None
    low_open: bool = False
    high_open: bool = False
    example: str = ""

    def accepts(self, v: float) -> bool:
        if self.low is not None and (v < self.low or (self.low_open and v == self.low)):
            return False
        if self.high is not None and (v > self.high or (self.high_open and v == self.high)):
            return False
        return True

    def range_text(self) -> str:
        lo = "" if self.low is None else f"{'>' if self.low_open else '≥'} {_num(self.low)}"
        hi = "" if self.high is None else f"{'<' if self.high_open else '≤'} {_num(self.high)}"
        return " and ".join(s for s in (lo, hi) if s)


def _num(v: float) -> str:
    """A bound or value as a user typed it: whole numbers in full (4294967295, not 4.29497e+09)."""
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else f"{v:g}"


_POSITIVE_M = dict(low=0.0, low_open=True, high=1e5)
_COUNT = dict(low=1)

#: option ranges by parameter name (the click destination): one meaning per name across every command.
#: A multi-number option has one rule per position (``sun``: azimuth, elevation).
RULES: dict[str, tuple[Rule, ...]] = {
    "posting_m": (Rule("a grid posting in metres", **_POSITIVE_M, example="0.5"),),
    "size_m": (Rule("a size in metres", **_POSITIVE_M, example="300"),),
    "gsd_m": (Rule("a ground sampling distance in metres", **_POSITIVE_M, example="0.5"),),
    "finest_cell_m": (Rule("a cell size in metres", **_POSITIVE_M, example="0.5"),),
    "side_min_m": (Rule("a rectangle side in metres", **_POSITIVE_M, example="6"),),
    "side_max_m": (Rule("a rectangle side in metres", **_POSITIVE_M, example="30"),),
    "segment_m": (Rule("a segment size in metres", **_POSITIVE_M, example="3"),),
    "occlusion_tol_m": (Rule("a height tolerance in metres", low=0.0, high=1e4, example="1"),),
    "dem_margin": (Rule("a height margin in metres", low=0.0, high=1e4, example="50"),),
    "above_m": (Rule("a height in metres", low=0.0, high=1e4, example="30"),),
    "timeout_s": (Rule("a time in seconds", low=0.0, low_open=True, example="300"),),
    "seed": (Rule("a random seed", low=0, high=2**32 - 1, example="0"),),
    "n_bins": (Rule("a number of bins", low=2, high=100_000, example="24"),),
    "supersample": (Rule("a supersampling factor (k×k rays per pixel)", low=1, high=8, example="2"),),
    "screen_tile": (Rule("a tile side in cells", low=64, example="128"),),
    "tile_size": (Rule("a tile side in cells", low=64, example="1024"),),
    "cell_px": (Rule("a grid cell side in pixels", low=2, example="16"),),
    "window": (Rule("a matching window side in pixels", low=3, high=101, example="7"),),
    "max_iter": (Rule("an iteration count", **_COUNT, example="250"),),
    "passes": (Rule("a number of passes", **_COUNT, example="5"),),
    "max_depth": (Rule("an octree depth", low=0, high=6, example="3"),),
    "init_depth": (Rule("an octree depth", low=0, high=6, example="1"),),
    "n_fit": (Rule("a sample size", **_COUNT, example="1000"),),
    "n_inducing": (Rule("a number of inducing points", **_COUNT, example="400"),),
    "batch": (Rule("a batch size", **_COUNT, example="20000"),),
    "min_region_cells": (Rule("a number of cells", **_COUNT, example="4"),),
    "gamma_3d": (Rule("a prior weight", low=0.0, example="1"),),
    "prior": (Rule("a prior probability", low=0.0, high=1.0, low_open=True, high_open=True, example="0.5"),),
    "prior_change": (Rule("a prior probability", low=0.0, high=1.0, low_open=True, high_open=True, example="0.5"),),
    "sigma": (Rule("a standard deviation", low=0.0, low_open=True, example="1"),),
    "sigma_prime": (Rule("a standard deviation", low=0.0, low_open=True, example="1"),),
    "fallback_threshold": (Rule("a height difference in metres", low=0.0, low_open=True, example="2"),),
    "sun": (
        Rule("a sun azimuth in degrees", low=0.0, high=360.0, example="135"),
        Rule("a sun elevation in degrees", low=0.0, high=90.0, low_open=True, example="45"),
    ),
    # map coordinates: |x| beyond 1e8 is on no planet in any CRS geocd reads (degrees or metres)
    "bounds": (Rule("a map coordinate", low=-1e8, high=1e8),) * 4,
}

#: options whose numbers must increase along the tuple, with what the positions are
ORDERED: dict[str, str] = {"height_range": "MIN MAX", "bounds": "LEFT BOTTOM RIGHT TOP"}


def _flag(param: click.Parameter) -> str:
    opts = [o for o in getattr(param, "opts", ()) if o.startswith("--")]
    return opts[0] if opts else (param.human_readable_name or str(param.name))


def _check_number(param: click.Parameter, v: Any, rule: Optional[Rule]) -> None:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return
    flag = _flag(param)
    if isinstance(v, float) and not math.isfinite(v):
        raise click.BadParameter(f"{v} is not a finite number", param=param)
    if rule is not None and not rule.accepts(v):
        hint = f" (e.g. {flag} {rule.example})" if rule.example else ""
        raise click.BadParameter(f"{_num(v)} is not {rule.what}: give a value {rule.range_text()}{hint}", param=param)


def _check_ordered(param: click.Parameter, values: tuple) -> None:
    if param.name == "bounds" and len(values) == 4:
        l, b, r, t = values
        if not (l < r and b < t):
            raise click.BadParameter(
                f"{l:g} {b:g} {r:g} {t:g} is not LEFT BOTTOM RIGHT TOP with left < right and bottom < top", param=param
            )
    elif len(values) == 2 and not values[0] < values[1]:
        raise click.BadParameter(
            f"{values[0]:g} {values[1]:g} is not {ORDERED[param.name]} with the first below the second", param=param
        )


def check_value(param: click.Parameter, value: Any) -> Any:
    """Check one parsed option value (a number, a tuple of numbers, or a tuple of those for ``multiple=True``)."""
    if value is None:
        return value
    rules = RULES.get(param.name or "")
    groups = value if (param.multiple and isinstance(value, tuple)) else (value,)
    for g in groups:
        items = g if isinstance(g, tuple) else (g,)
        for i, v in enumerate(items):
            _check_number(param, v, None if rules is None else rules[min(i, len(rules) - 1)])
        if isinstance(g, tuple) and param.name in ORDERED and all(isinstance(v, (int, float)) for v in g):
            _check_ordered(param, g)
    return value


def _wrap(param: click.Parameter) -> None:
    previous: Optional[Callable] = param.callback

    def callback(ctx: click.Context, p: click.Parameter, value: Any) -> Any:
        value = check_value(p, value)
        return previous(ctx, p, value) if previous is not None else value

    param.callback = callback


def _numeric(param: click.Parameter) -> bool:
    t = param.type
    kinds = t.types if isinstance(t, click.Tuple) else [t]
    return any(isinstance(k, (click.types.FloatParamType, click.types.IntParamType)) for k in kinds)


def harden_options(cmd: click.Command) -> click.Command:
    """Give every numeric option of ``cmd`` the shared checks (idempotent)."""
    if getattr(cmd, "_geocd_hardened", False):
        return cmd
    for p in cmd.params:
        if _numeric(p):
            _wrap(p)
    cmd._geocd_hardened = True  # type: ignore[attr-defined]
    return cmd
