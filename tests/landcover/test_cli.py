"""``geocd landcover train|predict|integrate`` end to end on a tiny orthoimage scene, and bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from geocd.cli import main

from .scene import CRS, write_scene


def _run(args):
    return CliRunner().invoke(main, ["--progress", "none", *args])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("lc")
    paths = write_scene(d)
    model = d / "model.joblib"
    r = _run(
        [
            "landcover",
            "train",
            "--labels",
            str(paths["labels"]),
            "--image",
            str(paths["image"]),
            "--positive",
            "vegetation",
            "--out",
            str(model),
        ]
    )
    assert r.exit_code == 0, r.output
    return d, paths, model


def test_train_writes_model_and_report(trained):
    d, paths, model = trained
    rep = json.loads(model.with_suffix(".json").read_text())
    assert rep["classes"] == ["other", "vegetation"]
    assert rep["samples_per_class"] == {"other": 465, "vegetation": 320}
    assert rep["polygons"] == 4


@pytest.mark.slow
def test_predict_and_integrate(trained):
    d, paths, model = trained
    out = d / "pred"
    r = _run(
        [
            "landcover",
            "predict",
            "--model",
            str(model),
            "--image",
            str(paths["image"]),
            "--dem",
            str(paths["dem"]),
            "--out",
            str(out),
        ]
    )
    assert r.exit_code == 0, r.output
    with rasterio.open(out / "landcover_ortho_proba.tif") as ds:
        assert ds.count == 2 and ds.descriptions == ("p_other", "p_vegetation")
        p = ds.read(2)
    with rasterio.open(out / "landcover_ground.tif") as ds:
        g = ds.read(1)
        profile = ds.profile
    truth = rasterio.open(paths["truth"]).read(1)
    assert np.mean((g > 0.5) == (truth == 1)) > 0.95
    assert np.nanmean(np.abs(p - g)) < 0.05
    # the detailed views see only the left two thirds; the coarse map is a noisy full cover
    det = g.copy()
    det[:, 64:] = np.nan
    coarse = np.clip(truth + np.random.default_rng(0).normal(0, 0.3, truth.shape), 0, 1).astype(np.float32)
    for name, a in (("det.tif", det), ("coarse.tif", coarse)):
        with rasterio.open(d / name, "w", **{**profile, "count": 1}) as ds:
            ds.write(a, 1)
    out2 = d / "gp"
    r = _run(
        [
            "landcover",
            "integrate",
            "--detailed",
            str(d / "det.tif"),
            "--coarse",
            str(d / "coarse.tif"),
            "--dem",
            str(paths["dem"]),
            "--n-fit",
            "200",
            "--inducing",
            "150",
            "--class-name",
            "vegetation",
            "--calibrate-folds",
            "3",
            "--truth",
            str(paths["truth"]),
            "--truth-values",
            "1",
            "--exclude-labels",
            str(paths["labels"]),
            "--out",
            str(out2),
        ]
    )
    assert r.exit_code == 0, r.output
    with rasterio.open(out2 / "landcover_probability.tif") as ds:
        assert ds.descriptions == ("p_vegetation",)
        m = ds.read(1)
        assert ds.overviews(1) is not None
    with rasterio.open(out2 / "landcover_sigma.tif") as ds:
        assert ds.descriptions == ("sigma", "sigma_obs", "sigma_calibrated", "mean_unclipped", "detailed")
        sd = ds.read(1)
    assert np.isfinite(m).all() and (m >= 0).all() and (m <= 1).all()
    # σ grows away from the observed cells
    assert np.median(sd[:, 80:]) > np.median(sd[:, :60])
    ab = json.loads((out2 / "landcover_ablation.json").read_text())
    assert ab["coarse alone (all cells)"]["f1_at_recall"] > 0.6
    assert (
        ab["GP: detailed + coarse + xy (all cells)"]["f1_at_recall"]
        >= ab["coarse alone (all cells)"]["f1_at_recall"] - 0.02
    )
    assert 0 < ab["observed_fraction"] < 1
    assert (out2 / "landcover_ablation.png").stat().st_size > 1000


def test_bad_inputs_are_clear_errors(trained, tmp_path):
    import geopandas as gpd
    from shapely.geometry import box

    d, paths, model = trained
    one = tmp_path / "one.gpkg"
    gpd.GeoDataFrame({"class": ["vegetation"]}, geometry=[box(500005, 4799910, 500015, 4799930)], crs=CRS).to_file(one)
    r = _run(
        [
            "landcover",
            "train",
            "--labels",
            str(one),
            "--image",
            str(paths["image"]),
            "--out",
            str(tmp_path / "m.joblib"),
        ]
    )
    assert r.exit_code == 2 and "single class" in r.output
    far = tmp_path / "far.gpkg"
    gpd.GeoDataFrame({"class": ["a", "b"]}, geometry=[box(0, 0, 5, 5), box(10, 10, 20, 20)], crs=CRS).to_file(far)
    r = _run(
        [
            "landcover",
            "train",
            "--labels",
            str(far),
            "--image",
            str(paths["image"]),
            "--out",
            str(tmp_path / "m.joblib"),
        ]
    )
    assert r.exit_code == 2 and "falls on a valid pixel of any image" in r.output
    tiny = tmp_path / "tiny.gpkg"
    gpd.GeoDataFrame(
        {"class": ["a", "b"]},
        geometry=[box(500005, 4799990, 500007, 4799992), box(500060, 4799990, 500062, 4799992)],
        crs=CRS,
    ).to_file(tiny)
    r = _run(
        [
            "landcover",
            "train",
            "--labels",
            str(tiny),
            "--image",
            str(paths["image"]),
            "--out",
            str(tmp_path / "m.joblib"),
        ]
    )
    assert r.exit_code == 2 and "labelled pixels for 17 features" in r.output
    assert not (tmp_path / "m.joblib").exists()
    r = _run(["landcover", "integrate", "--detailed", str(paths["image"]), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "--dem" in r.output


def test_a_model_from_elsewhere_needs_trust_model(trained, tmp_path, monkeypatch):
    import shutil

    from geocd.landcover import trust

    d, paths, model = trained
    # on another account (an empty trust list) the same file is someone else's model
    monkeypatch.setenv(trust.TRUST_ENV, str(tmp_path / "other_user_list"))
    given = shutil.copy(model, tmp_path / "given.joblib")
    out = tmp_path / "pred"
    args = ["landcover", "predict", "--model", str(given), "--image", str(paths["image"]), "--out", str(out)]
    r = _run(args)
    assert r.exit_code == 2, r.output
    errs = [ln for ln in r.stderr.splitlines() if ln.startswith("geocd: error:")]
    assert len(errs) == 1 and "not written by 'geocd landcover train'" in errs[0] and "--trust-model" in errs[0]
    assert not out.exists()
    r = _run([*args, "--trust-model"])
    assert r.exit_code == 0, r.output
    warns = [ln for ln in r.stderr.splitlines() if ln.startswith("geocd: warning:")]
    assert len(warns) == 1 and "runs whatever code its author put in it" in warns[0], r.stderr
    assert (out / "landcover_ortho_proba.tif").exists()
