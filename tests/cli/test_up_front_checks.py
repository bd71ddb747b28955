"""Inputs and options checked before any heavy work: mpp's --change-prior, synth's --supersample."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.cli.mpp import check_change_prior
from geocd.errors import ConfigError, CRSError, EmptyDataError, UnsupportedFormatError
from geocd.geodesy import AOIGrid
from geocd.io.raster import write_cog, write_image
from geocd.synth.generate import SynthParams

GRID = AOIGrid.from_bounds(500000.0, 4000000.0, 500040.0, 4000040.0, 1.0, "EPSG:32631")


def _prior(path, values, **kw):
    return write_cog(path, {"confidence": np.asarray(values, np.float32)}, GRID, **kw)


def test_change_prior_accepts_fractions_and_percent(tmp_path):
    v = np.random.default_rng(0).random(GRID.shape)
    v[:5] = np.nan
    check_change_prior(_prior(tmp_path / "f.tif", v))
    check_change_prior(_prior(tmp_path / "p.tif", 100 * v))


def test_change_prior_refusals(tmp_path):
    with pytest.raises(ConfigError, match=r"values -5..200; it must be a 0–1 or 0–100"):
        check_change_prior(
            _prior(tmp_path / "h.tif", np.linspace(-5, 200, GRID.shape[0] * GRID.shape[1]).reshape(GRID.shape))
        )
    with pytest.raises(EmptyDataError, match="no valid value"):
        check_change_prior(_prior(tmp_path / "n.tif", np.full(GRID.shape, np.nan)))
    (tmp_path / "g.tif").write_bytes(b"\x01\x02garbage" * 200)
    with pytest.raises(UnsupportedFormatError, match="g.tif"):
        check_change_prior(tmp_path / "g.tif")
    nogeo = write_image(tmp_path / "ng.tif", np.zeros((1, 10, 10), np.uint8))
    with pytest.raises(CRSError, match="has no CRS"):
        check_change_prior(nogeo)


@pytest.mark.parametrize("k", [0, 9, -1, 2.0, True])
def test_synth_supersample_is_checked_with_the_parameters(k):
    with pytest.raises(ConfigError, match="supersample must be a whole number within 1..8"):
        SynthParams.tiny(supersample=k)


def test_synth_supersample_in_range():
    assert SynthParams.tiny(supersample=3).supersample == 3


def test_mpp_refuses_a_ground_it_would_not_use(tmp_path):
    """--ground is read with --image-a/--image-b only: with a manifest it was ignored, silently."""
    from click.testing import CliRunner

    from geocd.cli import main
    from tests.reliability.scenes import error_lines, make_scene, write_dem_pair

    sc = make_scene(tmp_path / "scene")
    a, _ = write_dem_pair(tmp_path / "d")
    r = CliRunner().invoke(
        main, ["--progress", "none", "mpp", str(sc.manifest), "--ground", str(a), "--out", str(tmp_path / "O")]
    )
    assert r.exit_code == 2, r.output
    assert "--ground is the terrain for --image-a/--image-b" in error_lines(r.stderr)[0]
    assert not (tmp_path / "O").exists()
