"""Features, labels and the pixel classifier on a tiny synthetic image."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from geocd.errors import ConfigError, GeoCDError, UnsupportedFormatError
from geocd.landcover.classifier import LabelError, check_training_set, load_model, predict_proba, save_model, train
from geocd.landcover.features import FeatureSpec, pixel_features
from geocd.landcover.labels import class_list, pixel_layer_rows, rasterize_labels, read_labels

from .scene import cover, rgb, write_scene


@pytest.mark.parametrize("bands", [1, 3, 4])
def test_feature_names_match_stack(bands):
    spec = FeatureSpec(texture_sigmas_px=(1.0, 2.0))
    img = np.random.default_rng(0).integers(0, 255, (bands, 20, 24)).astype(np.uint8)
    F = pixel_features(img, np.ones((20, 24), bool), spec)
    assert F.shape == (len(spec.names(bands)), 20, 24)
    assert F.dtype == np.float32 and np.isfinite(F).all()


def test_features_ignore_gain_and_offset():
    """Per-band percentile normalisation: a view with another gain/offset gives the same features."""
    a = rgb(48).astype(np.float32)
    ok = np.ones((48, 48), bool)
    F1 = pixel_features(a, ok)
    F2 = pixel_features(a * 3.0 + 50.0, ok)
    np.testing.assert_allclose(F1, F2, atol=2e-3)


def test_patch_mean_variance_reference():
    """The 5×5 grey mean/variance features against a direct loop (interior pixels)."""
    rng = np.random.default_rng(1)
    img = rng.random((1, 15, 17)).astype(np.float32)
    spec = FeatureSpec(texture_sigmas_px=(), percentiles=(0.0, 100.0))
    F = pixel_features(img, np.ones((15, 17), bool), spec)
    g = (img[0] - img.min()) / (img.max() - img.min())
    for r, c in [(5, 5), (7, 9), (2, 2)]:
        w = g[r - 2 : r + 3, c - 2 : c + 3]
        assert F[1, r, c] == pytest.approx(w.mean(), abs=1e-5)
        assert F[2, r, c] == pytest.approx(w.var(), abs=1e-5)


def test_height_feature_needs_heights():
    with pytest.raises(ConfigError, match="height above ground"):
        pixel_features(rgb(16), np.ones((16, 16), bool), FeatureSpec(height_above_ground=True))


def _samples(n=64, seed=0):
    img = rgb(n, seed)
    F = pixel_features(img, np.ones((n, n), bool))
    y = cover(n).astype(np.int64)
    return F, y


@pytest.mark.parametrize("method", ["rf", "logreg", "svm"])
def test_classifier_separates_grass_from_road(method):
    F, y = _samples(64, 0)
    rng = np.random.default_rng(0)
    idx = rng.choice(y.size, 1500, replace=False)
    X = F.reshape(F.shape[0], -1).T[idx]
    m = train(X, y.ravel()[idx], ["other", "vegetation"], FeatureSpec(), 3, method=method)
    F2, y2 = _samples(64, 5)  # a new image of the same kind
    p = predict_proba(m, F2, np.ones(y2.shape, bool))
    assert p.shape == (2, 64, 64)
    np.testing.assert_allclose(p.sum(axis=0), 1.0, atol=1e-5)
    acc = np.mean((p[1] > 0.5) == (y2 == 1))
    assert acc > 0.9, acc


def test_model_roundtrip_and_spec_check(tmp_path):
    import joblib

    F, y = _samples(48)
    X = F.reshape(F.shape[0], -1).T
    m = train(X, y.ravel(), ["other", "vegetation"], FeatureSpec(), 3)
    path = save_model(m, tmp_path / "m.joblib")
    m2 = load_model(path)
    assert m2.classes == ["other", "vegetation"] and m2.feature_names == m.feature_names
    np.testing.assert_array_equal(
        predict_proba(m, F, np.ones(y.shape, bool)), predict_proba(m2, F, np.ones(y.shape, bool))
    )
    d = joblib.load(path)
    d["feature_names"] = d["feature_names"][:-1]
    joblib.dump(d, tmp_path / "bad.joblib")  # files geocd did not write: loaded only when trusted
    with pytest.raises(UnsupportedFormatError, match="feature list"), pytest.warns(UserWarning, match="trust"):
        load_model(tmp_path / "bad.joblib", trust=True)
    d["geocd_landcover_model"] = 99
    joblib.dump(d, tmp_path / "old.joblib")
    with pytest.raises(UnsupportedFormatError, match="format 99"), pytest.warns(UserWarning, match="trust"):
        load_model(tmp_path / "old.joblib", trust=True)
    (tmp_path / "junk.joblib").write_bytes(b"not a model")
    with pytest.raises(UnsupportedFormatError), pytest.warns(UserWarning, match="trust"):
        load_model(tmp_path / "junk.joblib", trust=True)


class _RunsCode:
    """Unpickling this creates a marker file (what a hostile model file would do)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_model_geocd_did_not_write_is_not_unpickled(tmp_path, monkeypatch):
    import joblib

    from geocd.errors import GeoCDError, UntrustedFileError
    from geocd.landcover import trust

    monkeypatch.setenv(trust.TRUST_ENV, str(tmp_path / "list" / "trusted"))
    F, y = _samples(32)
    m = train(F.reshape(F.shape[0], -1).T, y.ravel(), ["other", "vegetation"], FeatureSpec(), 3)
    path = save_model(m, tmp_path / "m.joblib")
    assert trust.sha256_of(path.read_bytes()) in trust.trusted_digests()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a model geocd wrote loads without a word
        assert load_model(path).classes == m.classes
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.joblib"
    joblib.dump({"geocd_landcover_model": 1, "estimator": _RunsCode(marker)}, evil)
    with pytest.raises(UntrustedFileError, match=r"not written by 'geocd landcover train'.*--trust-model") as ei:
        load_model(evil)
    assert isinstance(ei.value, GeoCDError) and isinstance(ei.value, PermissionError)
    assert not marker.exists()
    # a trusted model changed afterwards is no longer trusted
    path.write_bytes(path.read_bytes() + b"\0")
    with pytest.raises(UntrustedFileError):
        load_model(path)
    # the explicit override loads it, naming the risk
    with pytest.warns(UserWarning, match="runs whatever code"):
        with pytest.raises(UnsupportedFormatError):
            load_model(evil, trust=True)
    assert marker.exists()


def test_the_trust_list_lives_in_the_cache_and_a_broken_one_trusts_nothing(tmp_path, monkeypatch):
    from geocd.landcover import trust

    monkeypatch.delenv(trust.TRUST_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert trust.trust_list_path() == tmp_path / "cache" / "geocd" / "trusted_models"
    assert trust.trusted_digests() == set()
    (tmp_path / "cache" / "geocd").mkdir(parents=True)
    trust.trust_list_path().write_text("garbage\n" + "A" * 64 + " /x\n\0\0\n")
    assert trust.trusted_digests() == {"a" * 64}
    # a list that cannot be written: the model is still saved, with a warning that predict will ask
    monkeypatch.setenv(trust.TRUST_ENV, str(tmp_path / "no_dir_file"))
    (tmp_path / "no_dir_file").mkdir()
    F, y = _samples(32)
    m = train(F.reshape(F.shape[0], -1).T, y.ravel(), ["other", "vegetation"], FeatureSpec(), 3)
    with pytest.warns(UserWarning, match="--trust-model"):
        path = save_model(m, tmp_path / "m.joblib")
    assert path.exists()


def test_bad_training_sets():
    X = np.random.default_rng(0).random((40, 17)).astype(np.float32)
    with pytest.raises(LabelError, match="single class"):
        check_training_set(X, np.zeros(40, np.int64), ["other", "vegetation"])
    with pytest.raises(LabelError, match="only 10 labelled pixels for 17 features"):
        check_training_set(X[:10], np.arange(10) % 2, ["other", "vegetation"])
    with pytest.raises(LabelError, match="no labelled pixel"):
        check_training_set(X[:0], np.zeros(0, np.int64), ["a", "b"])
    assert isinstance(LabelError("x"), GeoCDError)


def test_labels_pixel_coordinates_qgis_sign(tmp_path):
    import geopandas as gpd
    from affine import Affine
    from shapely.geometry import box

    down = gpd.GeoDataFrame(
        {"label": ["a", "b"], "polygon_id": [0, 1]}, geometry=[box(2, 3, 6, 8), box(10, 10, 14, 12)]
    )
    up = down.copy()
    up["geometry"] = [box(2, -8, 6, -3), box(10, -12, 14, -10)]  # as QGIS shows an un-georeferenced raster
    c1, p1 = rasterize_labels(pixel_layer_rows(down, (16, 16)), (16, 16), Affine.identity(), ["a", "b"])
    c2, p2 = rasterize_labels(pixel_layer_rows(up, (16, 16)), (16, 16), Affine.identity(), ["a", "b"])
    np.testing.assert_array_equal(c1, c2)
    assert (c1 == 0).sum() == 4 * 5 and (c1 == 1).sum() == 4 * 2
    assert c1[3, 2] == 0 and c1[2, 2] == -1


def test_read_labels_fields(tmp_path):
    import geopandas as gpd
    from shapely.geometry import box

    p = tmp_path / "l.gpkg"
    gpd.GeoDataFrame({"KIND": ["veg", "road"]}, geometry=[box(0, 0, 1, 1), box(2, 2, 3, 3)], crs="EPSG:32631").to_file(
        p
    )
    with pytest.raises(ConfigError, match="no class attribute"):
        read_labels(p)
    g = read_labels(p, class_field="KIND")
    assert class_list(g, "veg") == ["road", "veg"]
    with pytest.raises(ConfigError, match="not in the labels"):
        class_list(g, "water")


def test_training_set_from_map_labels_on_an_orthoimage(tmp_path):
    from geocd.landcover.pipeline import load_image, training_set

    paths = write_scene(tmp_path)
    lab = read_labels(paths["labels"])
    classes = class_list(lab, "vegetation")
    X, y, g, per = training_set(lab, [load_image(paths["image"])], classes, FeatureSpec())
    assert per == {"ortho": X.shape[0]}
    assert np.bincount(y).tolist() == [15 * 15 + 12 * 20, 10 * 20 + 12 * 10]
    assert set(np.unique(g)) == {0, 1, 2, 3}


def test_labels_outside_every_image(tmp_path):
    import geopandas as gpd
    from shapely.geometry import box

    from geocd.landcover.pipeline import load_image, training_set

    paths = write_scene(tmp_path)
    far = tmp_path / "far.gpkg"
    gpd.GeoDataFrame(
        {"class": ["vegetation", "other"]}, geometry=[box(0, 0, 10, 10), box(20, 20, 30, 30)], crs="EPSG:32631"
    ).to_file(far)
    lab = read_labels(far)
    with pytest.raises(LabelError, match="none of the 2 label polygons falls on a valid pixel"):
        training_set(lab, [load_image(paths["image"])], class_list(lab), FeatureSpec())
