"""Every numeric option of every command: non-finite numbers and out-of-range values are one clean error.

The cases are read from the commands themselves, so a new command or option is covered with no edit here.
"""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from geocd.cli import SUBCOMMANDS, main
from geocd.cli.options import RULES, check_value

from tests.reliability.scenes import error_lines


def _commands():
    ctx = click.Context(main)
    out = []

    def walk(cmd, path):
        if isinstance(cmd, click.Group):
            for name, sub in sorted(cmd.commands.items()):
                walk(sub, [*path, name])
        else:
            out.append((path, cmd))

    for name in sorted(SUBCOMMANDS):
        walk(main.get_command(ctx, name), [name])
    return out


def _numeric_options():
    cases = []
    for path, cmd in _commands():
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.name.startswith("_geocd"):
                continue
            t = p.type
            kinds = t.types if isinstance(t, click.Tuple) else [t]
            if any(isinstance(k, click.types.FloatParamType) for k in kinds):
                cases.append((path, p))
    return cases


NUMERIC = _numeric_options()


def _invoke(path, args):
    # the bad option comes first on the command line: click processes it before any missing argument
    return CliRunner().invoke(main, ["--progress", "none", *path, *args])


def _value_args(p: click.Option, bad: str, position: int = 0) -> list[str]:
    n = max(p.nargs, 1)
    good = {"sun": ["135", "45"], "bounds": ["0", "0", "10", "10"], "height_range": ["0", "100"]}.get(p.name, ["1"] * n)
    vals = list(good[:n]) + ["1"] * (n - len(good))
    vals[position] = bad
    return [p.opts[0], *vals]


def test_there_are_numeric_options_in_most_commands():
    assert len(NUMERIC) >= 40
    assert len({tuple(path) for path, _ in NUMERIC}) >= 12


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
@pytest.mark.parametrize("path,param", NUMERIC, ids=[f"{' '.join(p)} {o.opts[0]}" for p, o in NUMERIC])
def test_non_finite_numbers_are_refused(path, param, bad):
    for pos in range(max(param.nargs, 1)):
        r = _invoke(path, _value_args(param, bad, pos))
        assert r.exit_code == 2, r.output
        errs = error_lines(r.stderr)
        assert len(errs) == 1, r.stderr
        assert param.opts[0] in errs[0] and "not a finite number" in errs[0], errs[0]
        assert "Traceback" not in r.output


def test_every_default_is_in_its_own_range():
    """A default outside the shared range would make a command fail although the user gave nothing."""
    checked = 0
    for _, cmd in _commands():
        for p in cmd.params:
            if (
                p.name in RULES
                and p.default is not None
                and not callable(p.default)
                and type(p.default).__name__ != "Sentinel"
            ):
                check_value(p, p.default)
                checked += 1
    assert checked >= 15


@pytest.mark.parametrize(
    "args,needle",
    [
        (["stereo", "--posting", "0", "m.yaml"], "'--posting': 0 is not a grid posting in metres"),
        (["ortho", "--posting", "-2", "i.tif"], "'--posting': -2 is not a grid posting in metres"),
        (["volume", "update", "--sun", "400", "100", "m"], "'--sun': 400 is not a sun azimuth in degrees"),
        (["volume", "update", "--sun", "100", "95", "m"], "'--sun': 95 is not a sun elevation in degrees"),
        (["mpp", "--seed", "-1", "m.yaml"], "'--seed': -1 is not a random seed"),
        (["synth", "--supersample", "0", "--out", "x"], "'--supersample': 0 is not a supersampling factor"),
        (["consistency", "--bins", "0", "a.tif"], "'--bins': 0 is not a number of bins"),
        (["run", "--screen-tile", "10"], "'--screen-tile': 10 is not a tile side in cells: give a value ≥ 64"),
        (["mpp", "--gamma-3d", "-1", "m.yaml"], "'--gamma-3d': -1 is not a prior weight"),
        (["landcover", "train", "--bounds", "0", "0", "1e308", "1", "x"], "'--bounds': 1e+308 is not a map coordinate"),
        (["landcover", "train", "--bounds", "10", "0", "0", "1", "x"], "is not LEFT BOTTOM RIGHT TOP"),
        (["stereo", "--height-range", "200", "100", "m.yaml"], "200 100 is not MIN MAX"),
        (["volume", "detect", "--prior", "1", "m"], "'--prior': 1 is not a prior probability"),
    ],
)
def test_out_of_range_values_are_refused_with_the_range(args, needle):
    r = CliRunner().invoke(main, ["--progress", "none", *args])
    assert r.exit_code == 2, r.output
    errs = error_lines(r.stderr)
    assert len(errs) == 1, r.stderr
    assert needle in errs[0], errs[0]
    assert errs[0].endswith(
        f"(see 'geocd {args[0] if args[0] not in ('volume', 'landcover') else ' '.join(args[:2])} --help')"
    ), errs[0]


@pytest.mark.parametrize(
    "args,needle",
    [
        (["--bogus"], "no such option '--bogus'"),
        (["nosuchcommand"], "no such command 'nosuchcommand'"),
        (["stereo", "--bogus", "m.yaml"], "no such option '--bogus'"),
        (["demdiff"], "missing argument 'DEMS...'"),
        (["stereo", "--score", "mdll", "m.yaml"], "invalid value for '--score'"),
    ],
)
def test_usage_errors_are_one_line(args, needle):
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2, r.output
    assert error_lines(r.stderr) == [ln for ln in r.stderr.splitlines() if ln.strip()], r.stderr
    assert len(error_lines(r.stderr)) == 1 and needle in error_lines(r.stderr)[0], r.stderr
    assert "Usage:" not in r.output


def test_debug_is_accepted_after_the_command(tmp_path):
    """`geocd CMD ... --debug` shows the traceback as `geocd --debug CMD` does (the exception is not translated)."""
    missing = str(tmp_path / "nope.tif")
    plain = CliRunner().invoke(main, ["--progress", "none", "demdiff", missing, missing])
    assert plain.exit_code == 2 and isinstance(plain.exception, SystemExit)
    for args in (["--debug", "demdiff", missing, missing], ["demdiff", missing, missing, "--debug"]):
        r = CliRunner().invoke(main, ["--progress", "none", *args])
        assert isinstance(r.exception, FileNotFoundError), (args, r.output)


def test_demdiff_refuses_dems_listed_newest_first(tmp_path):
    from tests.reliability.scenes import write_dem_pair

    a, b = write_dem_pair(tmp_path / "d")
    r = CliRunner().invoke(
        main,
        [
            "--progress",
            "none",
            "demdiff",
            str(a),
            str(b),
            "--dates",
            "2020-01-01,2019-01-01",
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert r.exit_code == 2, r.output
    assert "b (2019-01-01) is listed after a (2020-01-01) but dated before it" in error_lines(r.stderr)[0]
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())
