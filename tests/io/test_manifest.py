import datetime as dt
from pathlib import Path

import pytest
import yaml

from geocd.errors import GeoCDError, InputFileNotFoundError, ManifestError
from geocd.io.manifest import discover_manifest, load_manifest, manifest_to_dict


@pytest.fixture
def scene(tmp_path):
    (tmp_path / "img").mkdir()
    for n in ("a1", "a2", "b1"):
        (tmp_path / "img" / f"{n}.tif").write_bytes(b"")
    (tmp_path / "cam.json").write_text("{}")
    return tmp_path


def write(tmp_path, data):
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_valid_manifest_round_trip(scene):
    p = write(
        scene,
        {
            "name": "t",
            "aoi": {"crs": "EPSG:32631", "bounds": [0, 0, 10, 10], "posting_m": 0.5},
            "epochs": [
                {
                    "name": "A",
                    "date": "2020-01-02",
                    "images": ["img/a1.tif", {"path": "img/a2.tif", "camera": "cam.json"}],
                },
                {"name": "B", "date": dt.date(2021, 3, 4), "images": [{"path": "img/b1.tif"}]},
            ],
        },
    )
    m = load_manifest(p)
    assert [e.name for e in m.epochs] == ["A", "B"]
    assert m.epochs[0].date == dt.date(2020, 1, 2)
    assert m.epochs[0].images[1].camera == scene / "cam.json"
    assert m.aoi.posting_m == 0.5 and m.aoi.bounds == (0, 0, 10, 10)
    assert m.output is None and m.output_dir() == Path.cwd() / "geocd_out" / "t"
    # loading the folder finds scene.yaml; serialising and re-parsing gives the same manifest
    assert load_manifest(scene).epochs == m.epochs
    d = manifest_to_dict(m)
    assert d["epochs"][0]["images"][1] == {"path": "img/a2.tif", "camera": "cam.json"}
    assert load_manifest(write(scene, d)).epochs == m.epochs


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"epochs": []}, "non-empty list"),
        ({"epochs": [{"name": "A", "images": ["img/missing.tif"]}]}, "epochs[0].images[0].path: file"),
        (
            {"epochs": [{"name": "A", "images": ["img/a1.tif"]}, {"name": "A", "images": ["img/a2.tif"]}]},
            "duplicate epoch",
        ),
        ({"epochs": [{"name": "A", "date": "yesterday", "images": ["img/a1.tif"]}]}, "ISO 8601"),
        ({"epochs": [{"name": "A", "images": ["img/a1.tif"]}], "aoi": {"bounds": [1, 1, 0, 0]}}, "is empty"),
        ({"epochs": [{"name": "A", "images": ["img/a1.tif"]}], "colour": 1}, "colour: unknown key"),
        ({"epochs": [{"name": "A"}]}, "neither images nor a DEM"),
        ({"geocd_manifest": 7, "epochs": [{"name": "A", "images": ["img/a1.tif"]}]}, "version"),
    ],
)
def test_invalid_manifest_errors(scene, data, fragment):
    with pytest.raises(ManifestError) as ei:
        load_manifest(write(scene, data))
    assert fragment in str(ei.value)
    assert isinstance(ei.value, GeoCDError) and isinstance(ei.value, ValueError)


def test_syntax_error_and_missing(scene, tmp_path):
    p = scene / "bad.yaml"
    p.write_text("epochs: [unclosed")
    with pytest.raises(ManifestError, match="not valid YAML"):
        load_manifest(p)
    with pytest.raises(InputFileNotFoundError):
        load_manifest(tmp_path / "nope.yaml")


def test_discover_folder(tmp_path):
    for sub, names in (("2020-05-01_A", ["x.tif", "y.tif"]), ("2021-06-01_B", ["z.tif"])):
        (tmp_path / sub).mkdir()
        for n in names:
            (tmp_path / sub / n).write_bytes(b"")
    m = discover_manifest(tmp_path)
    assert [e.name for e in m.epochs] == ["2020-05-01_A", "2021-06-01_B"]
    assert m.epochs[0].date == dt.date(2020, 5, 1)
    assert len(m.epochs[0].images) == 2
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ManifestError, match="no manifest"):
        discover_manifest(empty)


def test_alias_bomb_manifest_is_refused_fast(scene):
    from tests.io.test_safe_yaml import BOMB

    p = scene / "bomb.yaml"
    p.write_text(BOMB + "epochs:\n  - {name: A, images: [img/a1.tif], sensor: *i}\n")
    t = __import__("time").perf_counter()
    with pytest.raises(ManifestError, match="expand to more than") as ei:
        load_manifest(p)
    assert __import__("time").perf_counter() - t < 2.0
    assert len(str(ei.value)) < 500


def test_duplicate_key_in_manifest(scene):
    p = scene / "dup.yaml"
    p.write_text("name: t\nepochs:\n  - name: A\n    images: [img/a1.tif]\n    name: B\n")
    with pytest.raises(ManifestError, match=r"duplicate key 'name' at line 5 \(first at line 3\)"):
        load_manifest(p)
    j = scene / "dup.json"
    j.write_text('{"name": "t", "name": "u", "epochs": [{"name": "A", "images": ["img/a1.tif"]}]}')
    with pytest.raises(ManifestError, match="duplicate key 'name'"):
        load_manifest(j)


def test_huge_value_is_not_expanded_into_the_message(scene):
    p = write(scene, {"epochs": [{"name": "A", "images": [{"path": ["x" * 10_000] * 50}]}]})
    with pytest.raises(ManifestError) as ei:
        load_manifest(p)
    assert "expected a file path" in str(ei.value) and len(str(ei.value)) < 600


def test_duplicate_image_name_in_an_epoch(scene):
    p = write(
        scene,
        {
            "epochs": [
                {"name": "A", "images": [{"path": "img/a1.tif", "name": "x"}, {"path": "img/a2.tif", "name": "x"}]}
            ]
        },
    )
    with pytest.raises(
        ManifestError,
        match=r"epochs\[0\].images\[1\] \(a2.tif\) and epochs\[0\].images\[0\] "
        r"\(a1.tif\) of epoch 'A' have the same image name 'x'",
    ):
        load_manifest(p)
    # the same stem in two folders of one epoch: the default names collide too
    (scene / "img2").mkdir()
    (scene / "img2" / "a1.tif").write_bytes(b"")
    with pytest.raises(ManifestError, match="same image name 'a1'"):
        load_manifest(write(scene, {"epochs": [{"name": "A", "images": ["img/a1.tif", "img2/a1.tif"]}]}))


def test_same_image_name_in_two_epochs_is_fine(scene):
    (scene / "img2").mkdir()
    (scene / "img2" / "a1.tif").write_bytes(b"x")
    m = load_manifest(
        write(scene, {"epochs": [{"name": "A", "images": ["img/a1.tif"]}, {"name": "B", "images": ["img2/a1.tif"]}]})
    )
    assert [e.images[0].name for e in m.epochs] == ["a1", "a1"]


@pytest.mark.parametrize("second", ["img/a1.tif", "img/../img/a1.tif", "link.tif", "hard.tif"])
def test_same_file_listed_twice(scene, second):
    import os

    (scene / "link.tif").symlink_to(scene / "img" / "a1.tif")
    os.link(scene / "img" / "a1.tif", scene / "hard.tif")
    p = write(
        scene,
        {
            "epochs": [
                {"name": "A", "images": ["img/a1.tif"]},
                {"name": "B", "images": [{"path": second, "name": "other"}]},
            ]
        },
    )
    with pytest.raises(
        ManifestError,
        match=r"epochs\[1\].images\[0\] \(.*\) and epochs\[0\].images\[0\] are the "
        "same file",
    ):
        load_manifest(p)


def test_discovered_folder_with_same_stem_twice(tmp_path):
    (tmp_path / "a.tif").write_bytes(b"1")
    (tmp_path / "a.tiff").write_bytes(b"2")
    with pytest.raises(ManifestError, match="same image name 'a'"):
        discover_manifest(tmp_path)
