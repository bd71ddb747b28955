"""Pixel classifier: a random forest (logistic regression and an SVM as the thesis's comparisons).

Arrays in, arrays out: :func:`train` takes a (n, n_features) sample matrix and
class labels; :func:`predict_proba` turns an image's feature stack into one
probability map per class. :func:`save_model` / :func:`load_model` keep a model
reusable (joblib), with the feature specification and a format version checked
on load, so a model is never applied to features it was not trained on. A joblib
file is a pickle: :func:`load_model` unpickles only models on this user's trust
list (:mod:`geocd.landcover.trust`; every saved model is added) unless told to
trust the file.

Training samples are labelled pixels of polygons a user drew; neighbouring
pixels of one polygon are strongly correlated, so method comparisons
(:func:`compare_methods`) hold out whole polygons (grouped cross-validation),
never random pixels.
"""

from __future__ import annotations

import io
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError, EmptyDataError, InputFileNotFoundError, UnsupportedFormatError
from ..io.atomic import atomic_path
from .features import FeatureSpec
from .trust import check_trusted, record_trusted, sha256_of

#: file format version of a saved model (bump when the stored fields change meaning)
MODEL_FORMAT = 1
METHODS = ("rf", "logreg", "svm")
METHOD_LABELS = {"rf": "random forest", "logreg": "logistic regression", "svm": "SVM (RBF)"}
#: at most this many training samples per class (random, seeded); the SVM uses fewer (its cost is ~n²)
MAX_SAMPLES_PER_CLASS = 20000
MAX_SVM_SAMPLES = 3000


class LabelError(EmptyDataError):
    """Training labels are unusable: outside every image, a single class, too few labelled pixels."""


@dataclass
class LandcoverModel:
    """A trained pixel classifier and everything needed to apply it again.

    Attributes
    ----------
    estimator : fitted scikit-learn classifier (``predict_proba``)
    method : "rf" | "logreg" | "svm"
    classes : list of str, the order of the probability bands
    spec : FeatureSpec
    n_bands : int, image bands the model expects
    feature_names : list of str
    gsd_m : float or None, median ground sampling distance of the training images (m)
    report : dict, training statistics (samples per class, cross-validated scores, feature importances)
    """

    estimator: Any
    method: str
    classes: list
    spec: FeatureSpec
    n_bands: int
    feature_names: list
    gsd_m: float | None = None
    report: dict = field(default_factory=dict)

    def class_index(self, name: str | None) -> int:
        """Index of class ``name`` (None: the positive class of a two-class model, else an error)."""
        if name is None:
            if len(self.classes) == 2:
                return 1
            raise ConfigError(
                f"the model has {len(self.classes)} classes {self.classes}; say which one to map (--class NAME)"
            )
        if str(name) not in self.classes:
            raise ConfigError(f"class {name!r} is not one of the model's classes {self.classes}")
        return self.classes.index(str(name))


def make_estimator(method: str, seed: int = 0, n_jobs: int = 1):
    """An unfitted scikit-learn classifier for ``method`` (feature scaling included where it matters)."""
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.ensemble import RandomForestClassifier
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    if method == "rf":
        return RandomForestClassifier(
            n_estimators=100, min_samples_leaf=3, class_weight="balanced", random_state=seed, n_jobs=n_jobs
        )
    if method == "logreg":
        return make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000, class_weight="balanced"))
    if method == "svm":
        svc = SVC(kernel="rbf", C=1.0, gamma="scale", class_weight="balanced", random_state=seed)
        return make_pipeline(StandardScaler(), CalibratedClassifierCV(svc, ensemble=False, cv=3))
    raise ConfigError(f"classifier method must be one of {METHODS}, got {method!r}")


def check_training_set(X: np.ndarray, y: np.ndarray, classes: list) -> None:
    """Raise :class:`LabelError` when the samples cannot train a classifier."""
    n, d = X.shape
    present = np.unique(y)
    if n == 0:
        raise LabelError(
            "no labelled pixel falls inside any image; draw the polygons over the images "
            "(same CRS, or pixel coordinates of the image) and check the layer's CRS"
        )
    if present.size < 2:
        only = classes[int(present[0])] if present.size else "?"
        raise LabelError(
            f"the labels hold a single class ({only!r}) inside the images; draw polygons of at least "
            "two classes (e.g. the condition and 'other')"
        )
    if n < d:
        raise LabelError(
            f"only {n} labelled pixels for {d} features; draw larger or more polygons "
            f"(at least {d} pixels, better hundreds per class)"
        )
    counts = np.bincount(y, minlength=len(classes))
    small = [classes[k] for k in present if counts[k] < 2]
    if small:
        raise LabelError(f"class(es) {small} have fewer than 2 labelled pixels; draw larger polygons")


def subsample(y: np.ndarray, per_class: int, seed: int = 0) -> np.ndarray:
    """Indices of at most ``per_class`` random samples of each class (sorted)."""
    rng = np.random.default_rng(seed)
    keep = []
    for c in np.unique(y):
        idx = np.flatnonzero(y == c)
        if idx.size > per_class:
            idx = rng.choice(idx, per_class, replace=False)
        keep.append(idx)
    return np.sort(np.concatenate(keep))


def fit_estimator(X: np.ndarray, y: np.ndarray, method: str, seed: int = 0, n_jobs: int = 1):
    """Fit one method on (X, y) with the per-method sample caps; returns the fitted estimator."""
    idx = subsample(y, MAX_SAMPLES_PER_CLASS, seed)
    if method == "svm":
        per = max(2, MAX_SVM_SAMPLES // max(1, np.unique(y).size))
        idx = idx[subsample(y[idx], per, seed)]
    est = make_estimator(method, seed, n_jobs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", category=UserWarning)
        est.fit(X[idx], y[idx])
    return est


def compare_methods(
    X: np.ndarray,
    y: np.ndarray,
    groups: np.ndarray,
    methods=METHODS,
    n_splits: int = 5,
    seed: int = 0,
    positive: int | None = None,
) -> dict:
    """Cross-validated scores of each method, holding out whole polygons (``groups``).

    Returns ``{method: {"f1": ..., "accuracy": ..., "folds": k}}``; F1 of the ``positive`` class
    (two-class: class 1) or macro-F1 for several classes.
    """
    from sklearn.metrics import accuracy_score, f1_score
    from sklearn.model_selection import StratifiedGroupKFold

    n_groups = np.unique(groups).size
    k = int(min(n_splits, n_groups))
    out: dict = {}
    if k < 2:
        return {"note": "one polygon only: no held-out comparison possible"}
    cv = StratifiedGroupKFold(n_splits=k, shuffle=True, random_state=seed)
    n_cls = np.unique(y).size
    for m in methods:
        preds = np.full(y.shape, -1)
        for tr, te in cv.split(X, y, groups):
            if np.unique(y[tr]).size < n_cls:
                continue
            est = fit_estimator(X[tr], y[tr], m, seed)
            preds[te] = est.classes_[np.argmax(est.predict_proba(X[te]), axis=1)]
        done = preds >= 0
        if not done.any():
            out[m] = {"note": "no fold held every class"}
            continue
        if n_cls == 2:
            pos = 1 if positive is None else positive
            f1 = f1_score(y[done], preds[done], pos_label=pos, zero_division=0)
        else:
            f1 = f1_score(y[done], preds[done], average="macro", zero_division=0)
        out[m] = {
            "f1": round(float(f1), 4),
            "accuracy": round(float(accuracy_score(y[done], preds[done])), 4),
            "folds": k,
            "samples": int(done.sum()),
        }
    return out


def train(
    X: np.ndarray,
    y: np.ndarray,
    classes: list,
    spec: FeatureSpec,
    n_bands: int,
    *,
    method: str = "rf",
    seed: int = 0,
    groups: np.ndarray | None = None,
    compare: bool = False,
    gsd_m: float | None = None,
    n_jobs: int = 1,
) -> LandcoverModel:
    """Train a pixel classifier.

    Parameters
    ----------
    X : float (n, n_features) samples; y : int (n,) class indices into ``classes``
    groups : int (n,), optional, polygon id of each sample (for :func:`compare_methods`)
    compare : also cross-validate every method (random forest, logistic regression, SVM)
    """
    if method not in METHODS:
        raise ConfigError(f"classifier method must be one of {METHODS}, got {method!r}")
    X = np.asarray(X, np.float32)
    y = np.asarray(y, np.int64)
    names = spec.names(n_bands)
    if X.ndim != 2 or X.shape[1] != len(names):
        raise ConfigError(f"samples have {X.shape[-1]} features, the spec gives {len(names)} ({names})")
    check_training_set(X, y, classes)
    est = fit_estimator(X, y, method, seed, n_jobs)
    counts = np.bincount(y, minlength=len(classes))
    report: dict = {"samples_per_class": {c: int(n) for c, n in zip(classes, counts)}, "method": method}
    if hasattr(est, "feature_importances_"):
        report["feature_importance"] = {n: round(float(v), 4) for n, v in zip(names, est.feature_importances_)}
    if compare and groups is not None:
        report["comparison"] = compare_methods(X, y, np.asarray(groups), seed=seed)
    return LandcoverModel(
        estimator=est,
        method=method,
        classes=[str(c) for c in classes],
        spec=spec,
        n_bands=int(n_bands),
        feature_names=names,
        gsd_m=gsd_m,
        report=report,
    )


def predict_proba(model: LandcoverModel, features: np.ndarray, valid: np.ndarray, batch: int = 200_000) -> np.ndarray:
    """Class probabilities of every valid pixel.

    Parameters
    ----------
    features : float32 (n_features, rows, cols) from :func:`~geocd.landcover.features.pixel_features`
    valid : bool (rows, cols)

    Returns
    -------
    float32 (n_classes, rows, cols), NaN where not valid; bands in ``model.classes`` order.
    """
    F = np.asarray(features)
    if F.shape[0] != len(model.feature_names):
        raise ConfigError(f"feature stack has {F.shape[0]} features; the model expects {len(model.feature_names)}")
    ok = np.asarray(valid, bool)
    out = np.full((len(model.classes),) + ok.shape, np.nan, np.float32)
    idx = np.flatnonzero(ok.ravel())
    flat = F.reshape(F.shape[0], -1)
    col_of = {int(c): k for k, c in enumerate(model.estimator.classes_)}
    for s in range(0, idx.size, batch):
        sel = idx[s : s + batch]
        p = model.estimator.predict_proba(np.ascontiguousarray(flat[:, sel].T))
        full = np.zeros((sel.size, len(model.classes)), np.float32)
        for c, k in col_of.items():
            full[:, c] = p[:, k]
        r, c_ = np.unravel_index(sel, ok.shape)
        out[:, r, c_] = full.T
    return out


# ---------------------------------------------------------------------------------------------
# persistence
# ---------------------------------------------------------------------------------------------
def save_model(model: LandcoverModel, path: os.PathLike | str, overwrite: bool = True) -> Path:
    """Write the model with joblib (atomically) and add it to this user's trusted-model list."""
    import joblib

    payload = {
        "geocd_landcover_model": MODEL_FORMAT,
        "geocd_version": __version__,
        "method": model.method,
        "classes": list(model.classes),
        "spec": model.spec.to_dict(),
        "n_bands": model.n_bands,
        "feature_names": list(model.feature_names),
        "gsd_m": model.gsd_m,
        "report": model.report,
        "estimator": model.estimator,
    }
    with atomic_path(path, overwrite=overwrite) as tmp:
        joblib.dump(payload, tmp, compress=3)
    record_trusted(path)
    return Path(path)


def load_model(path: os.PathLike | str, *, trust: bool = False) -> LandcoverModel:
    """Read a model written by :func:`save_model`, checking its format and feature specification.

    Parameters
    ----------
    path : the model file (joblib)
    trust : unpickle the file even when it is not on this user's trusted-model list (it was not written
        by :func:`save_model` here), with a warning: a pickle can run any code when loaded

    Raises
    ------
    UntrustedFileError
        The file is not on the trust list and ``trust`` is False (nothing of it was unpickled).
    """
    import joblib

    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(f"model {p} does not exist; train one with 'geocd landcover train'")
    data = p.read_bytes()  # hashed and unpickled from the same bytes: the file cannot change in between
    check_trusted(p, sha256_of(data), trust)
    try:
        d = joblib.load(io.BytesIO(data))
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a format problem
        raise UnsupportedFormatError(f"{p} is not a geocd land-cover model ({type(exc).__name__}: {exc})") from exc
    if not isinstance(d, dict) or "geocd_landcover_model" not in d:
        raise UnsupportedFormatError(f"{p} is not a geocd land-cover model; train one with 'geocd landcover train'")
    if d["geocd_landcover_model"] != MODEL_FORMAT:
        raise UnsupportedFormatError(
            f"{p} is a land-cover model of format {d['geocd_landcover_model']} (written by geocd "
            f"{d.get('geocd_version')}); this geocd reads format {MODEL_FORMAT}: retrain it"
        )
    try:
        spec = FeatureSpec.from_dict(d["spec"])
        names = spec.names(int(d["n_bands"]))
        method, classes = str(d["method"]), [str(c) for c in d["classes"]]
        stored_names = list(d["feature_names"])
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise UnsupportedFormatError(
            f"{p} is a damaged geocd land-cover model ({type(exc).__name__}: {exc}); "
            "retrain it with 'geocd landcover train'"
        ) from exc
    est = d.get("estimator")
    if not (hasattr(est, "predict_proba") and hasattr(est, "classes_")):
        raise UnsupportedFormatError(f"{p} holds no fitted classifier; retrain it with 'geocd landcover train'")
    if names != stored_names:
        raise UnsupportedFormatError(
            f"{p}: the model's feature list {stored_names} differs from what this geocd computes for its "
            f"feature specification ({names}); retrain the model with this version"
        )
    return LandcoverModel(
        estimator=est,
        method=method,
        classes=classes,
        spec=spec,
        n_bands=int(d["n_bands"]),
        feature_names=names,
        gsd_m=d.get("gsd_m"),
        report=d.get("report", {}),
    )
