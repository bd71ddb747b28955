"""torchvision-style VGG and ResNet built from ``torch.nn`` modules (test-only, independent of geocd's folding).

Used to make ``data/cnn_reference.npz`` (``python -m tests.screen.torch_reference [cnn] [effnet] [pth]``) and, when torch is
installed, to check geocd's numpy and torch forward passes against ``nn.Module`` networks loaded with
``load_state_dict(strict=True)`` in eval mode.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the small networks of the reference file: (name, geocd backbone, layer list / ResNet spec)
NETS = (
    ("vgg_small", "vgg", [8, 8, "M", 16, "M", 16, "M"]),
    ("vgg_small_bn", "vgg", [8, "M", 16, "M", 16, "M"]),
    ("resnet_small", "resnet", [8, 1, 1, 1]),
)
REF = Path(__file__).parent / "data" / "cnn_reference.npz"
#: EfficientNet-Lite0 (random weights, seed 3) through the efficientnet_lite_pytorch port, every stage and the head
EFFNET_REF = Path(__file__).parent / "data" / "effnet_reference.npz"
#: a small state_dict saved by torch.save in its zip and its legacy format (read without torch)
PTH_ZIP = Path(__file__).parent / "data" / "tiny_zip.pth"
PTH_LEGACY = Path(__file__).parent / "data" / "tiny_legacy.pth"


def vgg_module(cfg, bn: bool):
    import torch.nn as nn

    layers, cin = [], 3
    for x in cfg:
        if x == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers.append(nn.Conv2d(cin, x, 3, padding=1))
            if bn:
                layers.append(nn.BatchNorm2d(x))
            layers.append(nn.ReLU(inplace=False))
            cin = x
    m = nn.Module()
    m.features = nn.Sequential(*layers)
    return m


def vgg_pools(m, x):
    import torch.nn as nn

    out = []
    for layer in m.features:
        x = layer(x)
        if isinstance(layer, nn.MaxPool2d):
            out.append(x)
    return out


def resnet_module(base: int, blocks):
    import torch.nn as nn

    class Basic(nn.Module):
        def __init__(self, cin, planes, stride):
            super().__init__()
            self.conv1 = nn.Conv2d(cin, planes, 3, stride, 1, bias=False)
            self.bn1 = nn.BatchNorm2d(planes)
            self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
            self.bn2 = nn.BatchNorm2d(planes)
            self.relu = nn.ReLU()
            self.downsample = None
            if stride != 1 or cin != planes:
                self.downsample = nn.Sequential(nn.Conv2d(cin, planes, 1, stride, bias=False), nn.BatchNorm2d(planes))

        def forward(self, x):
            idn = x if self.downsample is None else self.downsample(x)
            y = self.relu(self.bn1(self.conv1(x)))
            return self.relu(self.bn2(self.conv2(y)) + idn)

    m = nn.Module()
    m.conv1 = nn.Conv2d(3, base, 7, 2, 3, bias=False)
    m.bn1 = nn.BatchNorm2d(base)
    m.relu = nn.ReLU()
    m.maxpool = nn.MaxPool2d(3, 2, 1)
    cin = base
    for i, nb in enumerate(blocks):
        planes = base * 2**i
        seq = []
        for j in range(nb):
            seq.append(Basic(cin, planes, 2 if (i > 0 and j == 0) else 1))
            cin = planes
        setattr(m, f"layer{i + 1}", nn.Sequential(*seq))
    m.n_stages = len(blocks)
    return m


def resnet_layers(m, x):
    x = m.maxpool(m.relu(m.bn1(m.conv1(x))))
    out = [x]
    for i in range(m.n_stages):
        x = getattr(m, f"layer{i + 1}")(x)
        out.append(x)
    return out


def module_for(name: str, spec):
    if name.startswith("vgg"):
        return vgg_module(spec, name.endswith("_bn"))
    return resnet_module(spec[0], spec[1:])


def reference_features(name, spec, sd, image01: np.ndarray) -> list[np.ndarray]:
    """Feature maps of every pooling layer from the nn.Module network with ``sd`` (strict load, eval mode)."""
    import torch

    from geocd.screen.cnn import prepare_input

    m = module_for(name, spec)
    m.load_state_dict({k: torch.from_numpy(np.asarray(v)) for k, v in sd.items()}, strict=True)
    m.eval()
    x = torch.from_numpy(prepare_input(image01))[None]
    with torch.inference_mode():
        outs = vgg_pools(m, x) if name.startswith("vgg") else resnet_layers(m, x)
    return [o[0].numpy() for o in outs]


def make(path: Path = REF) -> None:
    from geocd.screen.cnn import random_state_dict

    rng = np.random.default_rng(7)
    image = rng.random((3, 45, 53)).astype(np.float32)  # odd sizes: floor-mode pooling and padding edges
    out = {"image": image}
    for name, bb, spec in NETS:
        sd = random_state_dict(
            "vgg11_bn" if name.endswith("_bn") else ("vgg19" if bb == "vgg" else "resnet"), seed=3, widths=spec
        )
        for k, v in sd.items():
            out[f"{name}/sd/{k}"] = v
        for i, f in enumerate(reference_features(name, spec, sd, image)):
            out[f"{name}/out/{i}"] = f
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)


def make_effnet(path: Path = EFFNET_REF) -> None:
    """EfficientNet-Lite0 features from the ``efficientnet_lite_pytorch`` port (an independent torch.nn model of
    TensorFlow's network; needs ``pip install efficientnet_lite_pytorch torch``), dynamic "same" padding, odd sizes."""
    import torch
    from efficientnet_lite_pytorch import EfficientNet

    from geocd.screen.cnn import TF_MEAN, TF_STD, _lite_stages, prepare_input, random_state_dict

    sd = random_state_dict("efficientnet_lite0", seed=3)
    m = EfficientNet.from_name("efficientnet-lite0", image_size=None)  # None: padding from each input's size
    full = m.state_dict()
    m.load_state_dict(
        {**{k: v for k, v in full.items() if k.startswith("_fc")}, **{k: torch.from_numpy(v) for k, v in sd.items()}},
        strict=True,
    )
    m.eval()
    image = np.random.default_rng(7).random((3, 45, 53)).astype(np.float32)
    x = torch.from_numpy(prepare_input(image, True, TF_MEAN, TF_STD))[None]
    ends = np.cumsum([r for r, *_ in _lite_stages("efficientnet_lite0")])
    out = {"image": image}
    with torch.inference_mode():
        t = m._swish(m._bn0(m._conv_stem(x)))
        for i, blk in enumerate(m._blocks):
            t = blk(t)
            if i + 1 in ends:
                out[f"stage{int(np.searchsorted(ends, i + 1)) + 1}"] = t[0].numpy()
        out["head"] = m._swish(m._bn1(m._conv_head(t)))[0].numpy()
    np.savez_compressed(path, **out)


def make_pth() -> None:
    """The same small state_dict in torch.save's zip and legacy formats (float32, int64 and a strided view)."""
    import torch

    sd = tiny_state_dict()
    t = {k: torch.from_numpy(v) for k, v in sd.items()}
    t["features.0.weight_t"] = torch.from_numpy(sd["features.0.weight"]).transpose(0, 1)  # a non-contiguous view
    torch.save({"state_dict": t}, PTH_ZIP)
    torch.save(t, PTH_LEGACY, _use_new_zipfile_serialization=False)


def tiny_state_dict() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(2)
    return {
        "features.0.weight": rng.standard_normal((4, 3, 3, 3)).astype(np.float32),
        "features.0.bias": rng.standard_normal(4).astype(np.float32),
        "bn.num_batches_tracked": np.array(7, np.int64),
    }


if __name__ == "__main__":
    import sys

    what = sys.argv[1:] or ["cnn"]
    if "cnn" in what:
        make()
        print(f"wrote {REF} ({REF.stat().st_size} bytes)")
    if "effnet" in what:
        make_effnet()
        print(f"wrote {EFFNET_REF} ({EFFNET_REF.stat().st_size} bytes)")
    if "pth" in what:
        make_pth()
        print(f"wrote {PTH_ZIP}, {PTH_LEGACY}")
