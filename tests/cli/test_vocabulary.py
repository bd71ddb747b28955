"""One option vocabulary: every command's options read from the CLI and held to :mod:`geocd.cli.vocabulary`."""

from __future__ import annotations

import click
import pytest
from click.testing import CliRunner

from geocd.cli import SUBCOMMANDS, main
from geocd.cli.vocabulary import LEGACY, rewrite_legacy


def _commands() -> dict[str, click.Command]:
    ctx = click.Context(main)
    out: dict[str, click.Command] = {}

    def walk(cmd: click.Command, path: str) -> None:
        if isinstance(cmd, click.Group):
            for n, sub in cmd.commands.items():
                walk(sub, f"{path} {n}")
        else:
            out[path] = cmd

    for name in sorted(SUBCOMMANDS):
        walk(main.get_command(ctx, name), name)
    return out


COMMANDS = _commands()


def _options(cmd: click.Command) -> dict[str, click.Option]:
    """Visible options by every name they answer to (the shared --progress/--json/--debug left out)."""
    return {
        o: p
        for p in cmd.params
        if isinstance(p, click.Option) and not p.hidden and not (p.name or "").startswith("_geocd")
        for o in (*p.opts, *p.secondary_opts)
    }


def _kind(p: click.Option) -> str:
    """What an option takes, in words: flag, number, choice or text (a path or a name)."""
    if p.is_flag:
        return "flag"
    t = p.type
    if isinstance(t, click.Tuple):
        return (
            "numbers"
            if all(isinstance(k, (click.types.FloatParamType, click.types.IntParamType)) for k in t.types)
            else "texts"
        )
    if isinstance(
        t, (click.types.FloatParamType, click.types.IntParamType, click.types.FloatRange, click.types.IntRange)
    ):
        return "number"
    if isinstance(t, click.Choice):
        return "choice"
    return "text"


#: option names that no command shows any more (their old meanings live on as hidden aliases); an old name that
#: is a canonical name elsewhere (change's --epoch-a, probchange's --model) is retired in its own command only
RETIRED = {
    "--posting-m", "--size-m", "--gsd-m", "--datum-a", "--datum-b", "--dem-datum", "--dem-vertical-datum",
    "--images-a", "--images-b", "--view-a", "--view-b", "--pair", "--images", "-a", "-b",
}  # fmt: skip

#: commands that write nothing to a folder of their own: no --out
NO_OUT = {"info", "plugin-install", "volume update"}

#: the canonical names and what they take (every command that has the concept uses exactly this)
CANONICAL = {
    "--out": "text",
    "--epoch-a": "text",
    "--epoch-b": "text",
    "--epoch": "text",
    "--image": "text",
    "--image-a": "text",
    "--image-b": "text",
    "--pair-dem-a": "text",
    "--pair-dem-b": "text",
    "--vertical-datum": "text",
    "--posting": "number",
    "--scheduler": "text",
    "--confidence": "number",
    "--footprints": "text",
    "--model": "text",
    "--tile-size": "number",
}


def test_the_vocabulary_listing():
    """The listing the issue asks to see: every command's options (run with -s to read it)."""
    for path, cmd in COMMANDS.items():
        opts = sorted({p.opts[0] for p in _options(cmd).values()})
        print(f"geocd {path}: {' '.join(opts)}")
    assert len(COMMANDS) >= 20


@pytest.mark.parametrize("path", sorted(COMMANDS))
def test_no_retired_option_name_is_shown(path):
    shown = set(_options(COMMANDS[path]))
    retired = RETIRED | set(LEGACY.get(path, {}))
    assert not shown & retired, f"geocd {path} still shows {sorted(shown & retired)}"
    assert not {o for o in shown if o.endswith("-m")}, "options carry no unit suffix; the help gives the unit"


@pytest.mark.parametrize("path", sorted(COMMANDS))
def test_out_is_never_required_and_defaults_under_geocd_out(path):
    opts = _options(COMMANDS[path])
    if path in NO_OUT:
        assert "--out" not in opts or not opts["--out"].required
        return
    assert "--out" in opts, f"geocd {path} has no --out"
    out = opts["--out"]
    assert not out.required and out.default is None, f"geocd {path}: --out must be optional"
    assert "geocd_out" in (out.help or "") or "default" in (out.help or ""), f"geocd {path}: --out says no default"


def test_one_name_one_meaning_across_commands():
    """An option name means one kind of value in every command that has it (a flag is a flag everywhere, a
    number a number, a path or name text), and the canonical names take what CANONICAL says."""
    seen: dict[str, dict[str, str]] = {}
    for path, cmd in COMMANDS.items():
        for name, p in _options(cmd).items():
            seen.setdefault(name, {})[path] = _kind(p)
    clashes = {n: k for n, k in seen.items() if len(set(k.values())) > 1}
    assert not clashes, f"one option name, several kinds of value: {clashes}"
    for name, kind in CANONICAL.items():
        for path, k in seen.get(name, {}).items():
            assert k == kind, f"geocd {path} {name} takes {k}, not {kind}"


def test_one_scheduler_default():
    defaults = {
        path: _options(cmd)["--scheduler"].default for path, cmd in COMMANDS.items() if "--scheduler" in _options(cmd)
    }
    assert len(defaults) >= 4
    assert set(defaults.values()) == {None}, defaults  # None: auto, said the same way in every help
    helps = {path: _options(COMMANDS[path])["--scheduler"].help for path in defaults}
    assert all("auto (a local Dask cluster sized to the machine, the default" in h for h in helps.values()), helps


def test_datum_and_images_are_spelled_one_way():
    for path, cmd in COMMANDS.items():
        opts = _options(cmd)
        assert not {o for o in opts if "datum" in o} - {"--vertical-datum"}, path
        assert not {o for o in opts if o.startswith("--images") or o.startswith("--view-") and o != "--view-bands"}


@pytest.mark.parametrize(
    ("path", "old", "new"),
    [
        ("synth", ["--posting-m", "1"], ["--posting", "1"]),
        ("synth", ["--size-m=120"], ["--size=120"]),
        ("change", ["-a", "x.tif", "--epoch-b", "y.tif"], ["--pair-dem-a", "x.tif", "--pair-dem-b", "y.tif"]),
        ("probchange", ["m.yaml", "--images-a", "A1,A2"], ["m.yaml", "--image-a", "A1", "--image-a", "A2"]),
        ("screen", ["m.yaml", "--pair", "a1", "b1"], ["m.yaml", "--image-a", "a1", "--image-b", "b1"]),
        ("mpp", ["m.yaml", "--view-a", "v"], ["m.yaml", "--image-a", "v"]),
        ("landcover train", ["--dem-datum", "egm96"], ["--vertical-datum", "egm96"]),
        ("run", ["--epoch-a", "A"], ["--epoch-a", "A"]),  # no old names: left alone
        ("synth", ["--", "--posting-m"], ["--", "--posting-m"]),  # after --: not an option
    ],
)
def test_old_names_are_rewritten(path, old, new):
    notes: list[str] = []
    assert rewrite_legacy(path, old, note=notes.append) == new
    assert bool(notes) == (old != new)


def test_an_old_name_still_works_and_says_the_new_one():
    res = CliRunner().invoke(main, ["synth", "--posting-m", "1", "--help"])
    assert res.exit_code == 0, res.output
    assert "--posting-m is now spelled --posting" in res.output
    assert "--posting-m" not in res.output.split("Usage:", 1)[1]
