"""CNN pooling-layer grid features from weights the user names on disk (never downloaded).

Three backbone families, with the parameter names of the PyTorch models they come from so that
a ``state_dict`` exported from them (or any network built the same way) loads as is:

* **VGG** (``vgg11``, ``vgg13``, ``vgg16``, ``vgg19``, their ``_bn`` variants, or ``vgg``:
  the layer list read from the file): ``features.<i>.weight`` 3×3 convolutions, padding 1,
  ReLU, 2×2 max-pooling. Layers ``pool1`` … ``pool5`` (strides 2 … 32), as Sakurada's
  thesis (ch. 4) uses them.
* **ResNet** (``resnet18``, ``resnet34``, ``resnet50``, ``resnet101``, or ``resnet``: blocks
  read from the file): 7×7/2 stem, 3×3/2 max-pool, stages ``layer1`` … ``layer4`` of basic
  or bottleneck blocks (batch norm folded into the convolutions). Layers ``pool`` (the
  stem's max-pool, stride 4) and ``layer1`` … ``layer4`` (strides 4, 8, 16, 32).
* **EfficientNet-Lite** (``efficientnet_lite0`` … ``efficientnet_lite4``; the names of the
  ``efficientnet_lite_pytorch`` port of TensorFlow's models, ``_conv_stem``, ``_blocks.<i>``,
  ``_conv_head``): a 3×3/2 stem, seven stages of inverted-residual blocks (1×1 expansion,
  depthwise k×k, 1×1 projection, ReLU6, no squeeze-excitation) and a 1×1 head, with
  TensorFlow's "same" padding and batch-norm ε = 10⁻³. Layers ``stage1`` … ``stage7`` (strides
  2, 4, 8, 16, 16, 32, 32) and ``head`` (stride 32). Its input is scaled as TensorFlow's
  preprocessing does, (255·x − 127) / 128, not with the ImageNet mean and standard deviation.
  Lite0 is checked against the torch port and with trained weights; lite1–4 follow TensorFlow's
  width and depth rules and have not met real weights.

Weights files: ``.npz`` (one array per ``state_dict`` key: ``np.savez(path, **{k:
v.numpy() for k, v in model.state_dict().items()})``) — read with numpy alone — or a
PyTorch ``.pt``/``.pth`` state dict (read by PyTorch when installed, ``geocd[cnn]``, else by
:mod:`geocd.screen.torchfile`, which takes tensors only and runs no code). A file that
does not fit the backbone raises :class:`~geocd.errors.WeightsMismatchError` naming the
first parameter that differs, both shapes, and the backbone the file looks like.

Two forward passes compute the same features: a numpy one (im2col + BLAS, in row
chunks of bounded memory; always available) and a PyTorch one (``torch`` installed).
Both take the image as ``(bands, rows, cols)`` float in 0–1; one band is repeated to the
network's three, more than three keep the first three (RGB), then the ImageNet mean and
standard deviation are applied (``normalize``) as torchvision's weights expect.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ConfigError, InputFileNotFoundError, WeightsMismatchError
from .torchfile import TorchFileError, read_torch_file

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

VGG_CFGS: dict[str, list] = {
    "vgg11": [64, "M", 128, "M", 256, 256, "M", 512, 512, "M", 512, 512, "M"],
    "vgg13": [64, 64, "M", 128, 128, "M", 256, 256, "M", 512, 512, "M", 512, 512, "M"],
    "vgg16": [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"],
    "vgg19": [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512, "M"],
}
RESNET_CFGS: dict[str, tuple[str, list[int]]] = {
    "resnet18": ("basic", [2, 2, 2, 2]),
    "resnet34": ("basic", [3, 4, 6, 3]),
    "resnet50": ("bottleneck", [3, 4, 6, 3]),
    "resnet101": ("bottleneck", [3, 4, 23, 3]),
}
#: EfficientNet-Lite's stages at width and depth 1 (TensorFlow's efficientnet_lite_builder): repeats, kernel,
#: stride, expansion, input and output channels
EFFNET_LITE_STAGES = (
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
)
#: (width, depth) coefficients of each EfficientNet-Lite
EFFNET_LITE_CFGS = {
    "efficientnet_lite0": (1.0, 1.0),
    "efficientnet_lite1": (1.0, 1.1),
    "efficientnet_lite2": (1.1, 1.2),
    "efficientnet_lite3": (1.2, 1.4),
    "efficientnet_lite4": (1.4, 1.8),
}
BACKBONES = ("vgg", *VGG_CFGS, *(k + "_bn" for k in VGG_CFGS), "resnet", *RESNET_CFGS, *EFFNET_LITE_CFGS)
BN_EPS = 1e-5
BN_EPS_TF = 1e-3  # TensorFlow's models (EfficientNet-Lite)
#: TensorFlow's EfficientNet input scaling, (255 x − 127) / 128, as a mean and standard deviation of x in 0–1
TF_MEAN = (127 / 255,) * 3
TF_STD = (128 / 255,) * 3


# ---------------------------------------------------------------------------------------------
# weights files
# ---------------------------------------------------------------------------------------------
def load_weights(path: str | Path) -> dict[str, np.ndarray]:
    """A ``state_dict`` as {name: float32 array} from an ``.npz`` or a PyTorch ``.pt``/``.pth`` file."""
    p = Path(path)
    if not p.exists():
        raise InputFileNotFoundError(
            f"weights file {p} does not exist (geocd never downloads weights: export a "
            "state_dict to .npz or .pt and name it)"
        )
    if p.suffix.lower() == ".npz":
        try:
            with np.load(p, allow_pickle=False) as z:
                sd = {k: np.asarray(z[k]) for k in z.files}
        except Exception as exc:  # noqa: BLE001 - any unreadable archive is the same user error
            raise WeightsMismatchError(f"cannot read the weights archive {p}: {exc}") from exc
    elif p.suffix.lower() in (".pt", ".pth", ".bin"):
        if torch_available():
            import torch

            try:
                obj = torch.load(p, map_location="cpu", weights_only=True)
            except Exception as exc:  # noqa: BLE001
                raise WeightsMismatchError(f"cannot read the PyTorch weights {p}: {exc}") from exc
            obj = _tensors_to_numpy(obj)
        else:
            try:
                obj = read_torch_file(p)
            except (TorchFileError, OSError) as exc:
                raise WeightsMismatchError(
                    f"cannot read the PyTorch weights {p} without PyTorch: {exc}; install "
                    "the optional extra (pip install 'geocd[cnn]') or export the state_dict "
                    "to .npz"
                ) from exc
        for k in ("state_dict", "model", "model_state_dict"):
            if isinstance(obj, Mapping) and k in obj and isinstance(obj[k], Mapping):
                obj = obj[k]
        if not isinstance(obj, Mapping):
            raise WeightsMismatchError(
                f"{p} holds a {type(obj).__name__}, not a state_dict; save model.state_dict() instead of the model"
            )
        sd = {k: v for k, v in obj.items() if isinstance(v, np.ndarray)}
    else:
        raise ConfigError(f"weights file {p}: use .npz (numpy) or .pt/.pth (PyTorch state_dict)")
    sd = {re.sub(r"^(module\.|model\.|backbone\.)", "", k): v for k, v in sd.items()}
    return {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in sd.items()}


def _tensors_to_numpy(obj: Any) -> Any:
    """torch.load's containers with every tensor as a numpy array (as geocd's own reader returns them)."""
    if hasattr(obj, "detach"):
        return obj.detach().cpu().numpy()
    if isinstance(obj, Mapping):
        return {k: _tensors_to_numpy(v) for k, v in obj.items()}
    return obj


# ---------------------------------------------------------------------------------------------
# architectures
# ---------------------------------------------------------------------------------------------
@dataclass
class Conv:
    w: np.ndarray  # (out, in, kh, kw) float32 — (channels, 1, kh, kw) if depthwise — batch norm folded in
    b: np.ndarray  # (out,)
    stride: int = 1
    pad: int = 0
    same: bool = False  # TensorFlow's "same" padding (asymmetric at stride 2) instead of ``pad``
    depthwise: bool = False  # one kh × kw filter per channel (groups = channels)


@dataclass
class Block:
    convs: list[Conv]
    down: Conv | None = None


@dataclass
class MBConv:
    """An inverted-residual block: [1×1 expansion], depthwise k×k, 1×1 projection (linear), skip if shapes match."""

    expand: Conv | None
    depthwise: Conv
    project: Conv
    skip: bool


@dataclass
class Network:
    """A backbone with its weights: VGG (``layers``: Conv or "M"), ResNet (``stem``, ``stages`` of Block) or
    EfficientNet-Lite (``stem``, ``stages`` of MBConv, ``head``)."""

    family: str
    name: str
    layers: list = field(default_factory=list)
    stem: Conv | None = None
    stages: list[list[Any]] = field(default_factory=list)
    head: Conv | None = None
    in_channels: int = 3
    mean: tuple = IMAGENET_MEAN  # input scaling the weights expect (image in 0–1)
    std: tuple = IMAGENET_STD

    @property
    def layer_names(self) -> list[str]:
        if self.family == "vgg":
            return [f"pool{k + 1}" for k in range(sum(1 for x in self.layers if isinstance(x, str)))]
        if self.family == "efficientnet":
            return [*[f"stage{k + 1}" for k in range(len(self.stages))], "head"]
        return ["pool", *[f"layer{k + 1}" for k in range(len(self.stages))]]

    def stride(self, layer: str) -> int:
        """Pixels per feature cell at ``layer``."""
        self._check_layer(layer)
        if self.family == "vgg":
            return 2 ** int(layer[4:])
        if self.family == "efficientnet":
            n = len(self.stages) if layer == "head" else int(layer[5:])
            return self.stem.stride * int(np.prod([s[0].depthwise.stride for s in self.stages[:n]]))
        return 4 if layer == "pool" else 4 * 2 ** (int(layer[5:]) - 1)

    def receptive_field(self, layer: str) -> int:
        """Receptive field (pixels) of one cell of ``layer``."""
        self._check_layer(layer)
        rf, jump = 1, 1

        def step(k: int, s: int) -> None:
            nonlocal rf, jump
            rf += (k - 1) * jump
            jump *= s

        if self.family == "vgg":
            k = int(layer[4:])
            pools = 0
            for x in self.layers:
                if isinstance(x, str):
                    step(2, 2)
                    pools += 1
                    if pools == k:
                        break
                else:
                    step(x.w.shape[2], x.stride)
            return rf
        step(self.stem.w.shape[2], self.stem.stride)
        if self.family == "efficientnet":
            n = len(self.stages) if layer == "head" else int(layer[5:])
            for s in self.stages[:n]:
                for blk in s:
                    step(blk.depthwise.w.shape[2], blk.depthwise.stride)
            return rf
        step(3, 2)
        if layer == "pool":
            return rf
        for s in self.stages[: int(layer[5:])]:
            for blk in s:
                for c in blk.convs:
                    step(c.w.shape[2], c.stride)
        return rf

    def _check_layer(self, layer: str) -> None:
        if layer not in self.layer_names:
            raise ConfigError(
                f"layer {layer!r} is not a layer of the {self.name} backbone; its layers are {self.layer_names}"
            )


def _need(sd: Mapping[str, np.ndarray], key: str, shape: tuple | None, backbone: str, guess: str) -> np.ndarray:
    if key not in sd:
        near = sorted(k for k in sd if k.split(".")[0] == key.split(".")[0])[:4]
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: parameter {key!r} is missing"
            + (
                f" (the file has e.g. {near})"
                if near
                else f" (the file's parameters start with {sorted({k.split('.')[0] for k in sd})[:6]})"
            )
            + f"; the file looks like {guess}"
        )
    a = sd[key]
    if shape is not None and tuple(a.shape) != tuple(shape):
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: {key!r} has shape {tuple(a.shape)} in the "
            f"file but {backbone} expects {tuple(shape)}; the file looks like {guess}"
        )
    return a


def describe_weights(sd: Mapping[str, np.ndarray]) -> str:
    """What backbone a state_dict looks like (for error messages)."""
    if any(k.startswith("features.") for k in sd):
        convs = sorted(
            int(k.split(".")[1]) for k in sd if re.fullmatch(r"features\.\d+\.weight", k) and sd[k].ndim == 4
        )
        bn = any(k.endswith("running_mean") for k in sd)
        for name, cfg in VGG_CFGS.items():
            if sum(1 for x in cfg if x != "M") == len(convs):
                return f"{name}{'_bn' if bn else ''} ({len(convs)} convolutions)"
        return f"a VGG-style network with {len(convs)} convolutions" + (" and batch norm" if bn else "")
    if "conv1.weight" in sd and any(k.startswith("layer1.") for k in sd):
        blocks = [len({k.split(".")[1] for k in sd if k.startswith(f"layer{i}.")}) for i in range(1, 5)]
        blocks = [b for b in blocks if b]
        kind = "bottleneck" if any(k.endswith("conv3.weight") for k in sd) else "basic"
        for name, (kd, cfg) in RESNET_CFGS.items():
            if kd == kind and cfg == blocks:
                return name
        return f"a ResNet-style network ({kind} blocks {blocks})"
    if "_conv_stem.weight" in sd:
        n = len({k.split(".")[1] for k in sd if k.startswith("_blocks.")})
        se = any("_se_reduce" in k for k in sd)
        for name in EFFNET_LITE_CFGS:
            if not se and sum(r for r, *_ in _lite_stages(name)) == n:
                return f"{name} ({n} blocks)"
        return f"an EfficientNet-style network ({n} blocks{', with squeeze-excitation' if se else ''})"
    return (
        "no known backbone (neither torchvision VGG 'features.*', ResNet 'conv1/layer1.*' nor EfficientNet "
        "'_conv_stem/_blocks.*' names)"
    )


def _fold_bn(w: np.ndarray, b: np.ndarray | None, sd, prefix: str, backbone: str, guess: str, eps: float = BN_EPS):
    g = _need(sd, f"{prefix}.weight", (w.shape[0],), backbone, guess)
    beta = _need(sd, f"{prefix}.bias", (w.shape[0],), backbone, guess)
    mu = _need(sd, f"{prefix}.running_mean", (w.shape[0],), backbone, guess)
    var = _need(sd, f"{prefix}.running_var", (w.shape[0],), backbone, guess)
    s = g / np.sqrt(var + eps)
    b0 = b if b is not None else np.zeros(w.shape[0], np.float32)
    return (w * s[:, None, None, None]).astype(np.float32), ((b0 - mu) * s + beta).astype(np.float32)


def _vgg_from_state(sd, backbone: str) -> Network:
    guess = describe_weights(sd)
    bn = backbone.endswith("_bn")
    base = backbone[:-3] if bn else backbone
    if base == "vgg":  # read the layer list from the file
        idx = sorted(int(k.split(".")[1]) for k in sd if re.fullmatch(r"features\.\d+\.weight", k) and sd[k].ndim == 4)
        if not idx:
            raise WeightsMismatchError(
                f"the weights file does not fit a VGG backbone: no 'features.<i>.weight' "
                f"convolutions; the file looks like {guess}"
            )
        bn = any(k.startswith("features.") and k.endswith("running_mean") for k in sd)
        per = 3 if bn else 2  # conv, [bn], relu
        cfg: list = []
        for j, i in enumerate(idx):
            cfg.append(int(sd[f"features.{i}.weight"].shape[0]))
            nxt = idx[j + 1] if j + 1 < len(idx) else None
            if nxt is None or nxt - i > per:
                cfg.append("M")
    elif base in VGG_CFGS:
        cfg = VGG_CFGS[base]
    else:
        raise ConfigError(f"unknown backbone {backbone!r}; known: {', '.join(BACKBONES)}")
    layers: list = []
    i, cin = 0, 3
    for x in cfg:
        if x == "M":
            layers.append("M")
            i += 1
            continue
        w = _need(sd, f"features.{i}.weight", (x, cin, 3, 3), backbone, guess)
        b = _need(sd, f"features.{i}.bias", (x,), backbone, guess)
        if bn:
            w, b = _fold_bn(w, b, sd, f"features.{i + 1}", backbone, guess)
        layers.append(Conv(w.astype(np.float32), b.astype(np.float32), 1, 1))
        i += 3 if bn else 2
        cin = x
    return Network("vgg", backbone, layers=layers)


def _resnet_from_state(sd, backbone: str) -> Network:
    guess = describe_weights(sd)
    if backbone == "resnet":
        kind = "bottleneck" if any(k.endswith("conv3.weight") for k in sd) else "basic"
        blocks = [len({k.split(".")[1] for k in sd if k.startswith(f"layer{i}.")}) for i in range(1, 5)]
        blocks = [b for b in blocks if b]
        if not blocks:
            raise WeightsMismatchError(
                f"the weights file does not fit a ResNet backbone: no 'layer1.*' "
                f"parameters; the file looks like {guess}"
            )
    elif backbone in RESNET_CFGS:
        kind, blocks = RESNET_CFGS[backbone]
    else:
        raise ConfigError(f"unknown backbone {backbone!r}; known: {', '.join(BACKBONES)}")
    w1 = _need(sd, "conv1.weight", None, backbone, guess)
    if w1.ndim != 4 or w1.shape[1] != 3:
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: 'conv1.weight' has "
            f"shape {tuple(w1.shape)}, expected (C, 3, k, k); the file looks like {guess}"
        )
    w, b = _fold_bn(w1, None, sd, "bn1", backbone, guess)
    stem = Conv(w, b, 2, w1.shape[2] // 2)
    width = w1.shape[0]
    cin = width
    stages = []
    expansion = 4 if kind == "bottleneck" else 1
    for si, nb in enumerate(blocks):
        planes = None
        stage = []
        for bi in range(nb):
            p = f"layer{si + 1}.{bi}"
            stride = 2 if (si > 0 and bi == 0) else 1
            c1 = _need(sd, f"{p}.conv1.weight", None, backbone, guess)
            if planes is None:
                planes = c1.shape[0]
                if planes != width * 2**si:
                    # widths need not be torchvision's; only the chain of shapes must be consistent
                    pass
            convs = []
            if kind == "basic":
                shapes = [(planes, cin, 3, 3), (planes, planes, 3, 3)]
                strides, pads = [stride, 1], [1, 1]
                names = ["conv1", "conv2"]
                cout = planes
            else:
                shapes = [(planes, cin, 1, 1), (planes, planes, 3, 3), (planes * expansion, planes, 1, 1)]
                strides, pads = [1, stride, 1], [0, 1, 0]
                names = ["conv1", "conv2", "conv3"]
                cout = planes * expansion
            for n, shp, s, pd in zip(names, shapes, strides, pads):
                cw = _need(sd, f"{p}.{n}.weight", shp, backbone, guess)
                fw, fb = _fold_bn(cw, None, sd, f"{p}.bn{n[-1]}", backbone, guess)
                convs.append(Conv(fw, fb, s, pd))
            down = None
            if f"{p}.downsample.0.weight" in sd or stride != 1 or cin != cout:
                dw = _need(sd, f"{p}.downsample.0.weight", (cout, cin, 1, 1), backbone, guess)
                fw, fb = _fold_bn(dw, None, sd, f"{p}.downsample.1", backbone, guess)
                down = Conv(fw, fb, stride, 0)
            stage.append(Block(convs, down))
            cin = cout
        stages.append(stage)
    extra = [k for k in sd if k.startswith(f"layer{len(blocks) + 1}.")]
    if extra:
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: it has a stage "
            f"layer{len(blocks) + 1} ({extra[0]!r}); the file looks like {guess}"
        )
    return Network("resnet", backbone, stem=stem, stages=stages)


def _round_filters(filters: int, width: float) -> int:
    """TensorFlow's channel rounding: width-scaled, to a multiple of 8, never below 90 % of the scaled value."""
    if width == 1.0:
        return filters
    f = filters * width
    new = max(8, int(f + 4) // 8 * 8)
    return int(new + 8 if new < 0.9 * f else new)


def _lite_stages(backbone: str) -> list[tuple[int, int, int, int, int, int]]:
    """(repeats, kernel, stride, expansion, in, out) of each stage of an EfficientNet-Lite (stem and head fixed)."""
    width, depth = EFFNET_LITE_CFGS[backbone]
    out = []
    for i, (r, k, s, e, cin, cout) in enumerate(EFFNET_LITE_STAGES):
        last = i in (0, len(EFFNET_LITE_STAGES) - 1)
        out.append(
            (
                r if last else int(math.ceil(depth * r)),
                k,
                s,
                e,
                32 if i == 0 else _round_filters(cin, width),
                _round_filters(cout, width),
            )
        )
    return out


def _lite_blocks(backbone: str):
    """Every inverted-residual block of an EfficientNet-Lite in order: (stage, index, kernel, stride, expansion,
    input, expanded and output channels)."""
    i = 0
    for si, (r, k, s, e, cin, cout) in enumerate(_lite_stages(backbone)):
        for j in range(r):
            c_in = cin if j == 0 else cout
            yield si, i, k, s if j == 0 else 1, e, c_in, c_in * e, cout
            i += 1


def _effnet_from_state(sd, backbone: str) -> Network:
    guess = describe_weights(sd)
    if backbone not in EFFNET_LITE_CFGS:
        raise ConfigError(f"unknown backbone {backbone!r}; known: {', '.join(BACKBONES)}")
    if any("_se_reduce" in k for k in sd):
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: it has squeeze-excitation "
            f"layers (an EfficientNet-B, not -Lite); the file looks like {guess}"
        )

    def conv_bn(prefix: str, bn: str, shape: tuple, stride: int = 1, depthwise: bool = False) -> Conv:
        w = _need(sd, f"{prefix}.weight", shape, backbone, guess)
        fw, fb = _fold_bn(w, None, sd, bn, backbone, guess, BN_EPS_TF)
        return Conv(fw, fb, stride, 0, same=True, depthwise=depthwise)

    stem = conv_bn("_conv_stem", "_bn0", (32, 3, 3, 3), 2)
    stages: list[list[MBConv]] = [[] for _ in EFFNET_LITE_STAGES]
    n = 0
    for si, i, k, stride, e, c_in, mid, cout in _lite_blocks(backbone):
        p = f"_blocks.{i}"
        expand = conv_bn(f"{p}._expand_conv", f"{p}._bn0", (mid, c_in, 1, 1)) if e != 1 else None
        dw = conv_bn(f"{p}._depthwise_conv", f"{p}._bn1", (mid, 1, k, k), stride, depthwise=True)
        proj = conv_bn(f"{p}._project_conv", f"{p}._bn2", (cout, mid, 1, 1))
        stages[si].append(MBConv(expand, dw, proj, skip=(stride == 1 and c_in == cout)))
        n = i + 1
    extra = sorted({int(key.split(".")[1]) for key in sd if key.startswith("_blocks.")} - set(range(n)))
    if extra:
        raise WeightsMismatchError(
            f"the weights file does not fit the {backbone} backbone: it has more blocks "
            f"('_blocks.{extra[0]}' is not part of {backbone}); the file looks like {guess}"
        )
    head = conv_bn("_conv_head", "_bn1", (1280, stages[-1][-1].project.w.shape[0], 1, 1))
    return Network("efficientnet", backbone, stem=stem, stages=stages, head=head, mean=TF_MEAN, std=TF_STD)


def build_network(backbone: str, weights: str | Path | Mapping[str, np.ndarray]) -> Network:
    """The backbone ``backbone`` with the weights of a file (or a state_dict mapping).

    Raises
    ------
    WeightsMismatchError
        The file's parameters do not fit the backbone (the message names the parameter, both
        shapes and what the file looks like).
    """
    sd = dict(weights) if isinstance(weights, Mapping) else load_weights(weights)
    sd = {k: np.asarray(v) for k, v in sd.items()}
    bb = backbone.lower()
    if bb.startswith("vgg"):
        net = _vgg_from_state(sd, bb)
    elif bb.startswith("resnet"):
        net = _resnet_from_state(sd, bb)
    elif bb.startswith("efficientnet"):
        net = _effnet_from_state(sd, bb)
    else:
        raise ConfigError(f"unknown backbone {backbone!r}; known: {', '.join(BACKBONES)}")
    if bb in VGG_CFGS or bb in RESNET_CFGS or bb.endswith("_bn"):
        # a named backbone must use the whole file's feature part: extra convolutions mean another depth
        used = _used_keys(net, sd)
        if bb.startswith("vgg"):
            extra = [k for k in sd if k.startswith("features.") and k not in used]
            if extra:
                raise WeightsMismatchError(
                    f"the weights file does not fit the {backbone} backbone: it has more layers ({extra[0]!r} is "
                    f"not part of {backbone}); the file looks like {describe_weights(sd)}"
                )
    return net


def _used_keys(net: Network, sd) -> set[str]:
    used = set()
    if net.family == "vgg":
        i = 0
        bn = net.name.endswith("_bn")
        for x in net.layers:
            if isinstance(x, str):
                i += 1
                continue
            used |= {f"features.{i}.weight", f"features.{i}.bias"}
            if bn:
                used |= {
                    f"features.{i + 1}.{s}"
                    for s in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
                }
            i += 3 if bn else 2
    return used


# ---------------------------------------------------------------------------------------------
# forward passes
# ---------------------------------------------------------------------------------------------
def prepare_input(
    image: np.ndarray, normalize: bool = True, mean: tuple = IMAGENET_MEAN, std: tuple = IMAGENET_STD
) -> np.ndarray:
    """(bands, rows, cols) float 0–1 → (3, rows, cols) float32 network input (``mean``, ``std``: per band)."""
    x = np.asarray(image, np.float32)
    if x.ndim == 2:
        x = x[None]
    if x.shape[0] == 1:
        x = np.repeat(x, 3, axis=0)
    elif x.shape[0] == 2:
        x = np.concatenate([x, x[:1]], axis=0)
    x = x[:3]
    if normalize:
        x = (x - np.asarray(mean, np.float32)[:, None, None]) / np.asarray(std, np.float32)[:, None, None]
    return np.ascontiguousarray(x, np.float32)


def same_padding(n: int, k: int, s: int) -> tuple[int, int]:
    """TensorFlow's "same" padding of one axis of length ``n``: (before, after); the extra cell goes after."""
    total = max((int(math.ceil(n / s)) - 1) * s + k - n, 0)
    return total // 2, total - total // 2


def _same_pads(h: int, w: int, c: Conv) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) "same" padding of an (h, w) input for convolution ``c``."""
    return (*same_padding(h, c.w.shape[2], c.stride), *same_padding(w, c.w.shape[3], c.stride))


def relu6(x: np.ndarray) -> np.ndarray:
    return np.clip(x, 0.0, 6.0)


def _depthwise_np(x: np.ndarray, c: Conv) -> np.ndarray:
    """Depthwise convolution: channel i with its own kh × kw filter (zero padding ``c.pad``)."""
    C, H, W = x.shape
    if c.w.shape[0] != C:
        raise WeightsMismatchError(
            f"a depthwise convolution expects {c.w.shape[0]} channels, the previous layer gives {C}"
        )
    _, _, kh, kw = c.w.shape
    p, s = c.pad, c.stride
    xp = np.pad(x, ((0, 0), (p, p), (p, p))) if p else x
    Ho = (H + 2 * p - kh) // s + 1
    Wo = (W + 2 * p - kw) // s + 1
    out = np.zeros((C, Ho, Wo), np.float32)
    for i in range(kh):
        for j in range(kw):
            out += xp[:, i : i + s * (Ho - 1) + 1 : s, j : j + s * (Wo - 1) + 1 : s] * c.w[:, 0, i, j][:, None, None]
    out += c.b[:, None, None]
    return out


def conv2d_np(x: np.ndarray, c: Conv, max_bytes: int = 64 << 20) -> np.ndarray:
    """2-D convolution (cross-correlation, as PyTorch) of (C, H, W) with zero padding; im2col in row chunks."""
    cin, H, W = x.shape
    cout, cin_w, kh, kw = c.w.shape
    if c.same:
        t, bt, lf, rt = _same_pads(H, W, c)
        return conv2d_np(
            np.pad(x, ((0, 0), (t, bt), (lf, rt))), Conv(c.w, c.b, c.stride, 0, depthwise=c.depthwise), max_bytes
        )
    if c.depthwise:
        return _depthwise_np(x, c)
    if kh == kw == 1 and c.stride == 1 and c.pad == 0 and cin == cin_w:  # pointwise: one matrix product
        out = (c.w.reshape(cout, cin) @ x.reshape(cin, -1)).reshape(cout, H, W)
        return out + c.b[:, None, None]
    if cin != cin_w:
        raise WeightsMismatchError(f"a convolution expects {cin_w} input channels, the previous layer gives {cin}")
    p, s = c.pad, c.stride
    xp = np.pad(x, ((0, 0), (p, p), (p, p))) if p else x
    Ho = (H + 2 * p - kh) // s + 1
    Wo = (W + 2 * p - kw) // s + 1
    out = np.empty((cout, Ho, Wo), np.float32)
    wm = c.w.reshape(cout, -1)
    per_row = cin * kh * kw * Wo * 4
    rows = max(1, int(max_bytes // max(per_row, 1)))
    for r0 in range(0, Ho, rows):
        r1 = min(Ho, r0 + rows)
        sl = xp[:, r0 * s : (r1 - 1) * s + kh, :]
        win = np.lib.stride_tricks.sliding_window_view(sl, (kh, kw), axis=(1, 2))[:, ::s, ::s]
        win = win[:, : r1 - r0, :Wo]  # (C, h, Wo, kh, kw)
        cols = np.ascontiguousarray(win.transpose(0, 3, 4, 1, 2)).reshape(cin * kh * kw, -1)
        out[:, r0:r1, :] = (wm @ cols).reshape(cout, r1 - r0, Wo)
    out += c.b[:, None, None]
    return out


def maxpool_np(x: np.ndarray, k: int, s: int, pad: int = 0) -> np.ndarray:
    """Max-pooling (PyTorch's floor mode; padding with −inf)."""
    if pad:
        x = np.pad(x, ((0, 0), (pad, pad), (pad, pad)), constant_values=-np.inf)
    C, H, W = x.shape
    Ho, Wo = (H - k) // s + 1, (W - k) // s + 1
    win = np.lib.stride_tricks.sliding_window_view(x, (k, k), axis=(1, 2))[:, ::s, ::s][:, :Ho, :Wo]
    return win.max(axis=(3, 4)).astype(np.float32)


def forward_np(net: Network, x: np.ndarray, layers: list[str]) -> dict[str, np.ndarray]:
    """Feature maps (C, h, w) at ``layers`` for a prepared input (3, H, W); numpy only."""
    want = set(layers)
    for ly in layers:
        net._check_layer(ly)
    out: dict[str, np.ndarray] = {}
    if net.family == "vgg":
        k = 0
        for L in net.layers:
            if isinstance(L, str):
                x = maxpool_np(x, 2, 2)
                k += 1
                if f"pool{k}" in want:
                    out[f"pool{k}"] = x
                if len(out) == len(want):
                    break
            else:
                x = np.maximum(conv2d_np(x, L), 0.0)
        return out
    if net.family == "efficientnet":
        x = relu6(conv2d_np(x, net.stem))
        for si, stage in enumerate(net.stages):
            for blk in stage:
                y = relu6(conv2d_np(x, blk.expand)) if blk.expand is not None else x
                y = conv2d_np(relu6(conv2d_np(y, blk.depthwise)), blk.project)
                x = y + x if blk.skip else y
            if f"stage{si + 1}" in want:
                out[f"stage{si + 1}"] = x
            if len(out) == len(want):
                return out
        out["head"] = relu6(conv2d_np(x, net.head))
        return out
    x = np.maximum(conv2d_np(x, net.stem), 0.0)
    x = maxpool_np(x, 3, 2, 1)
    if "pool" in want:
        out["pool"] = x
    for si, stage in enumerate(net.stages):
        if len(out) == len(want):
            break
        for blk in stage:
            idn = conv2d_np(x, blk.down) if blk.down is not None else x
            y = x
            for j, c in enumerate(blk.convs):
                y = conv2d_np(y, c)
                if j < len(blk.convs) - 1:
                    y = np.maximum(y, 0.0)
            x = np.maximum(y + idn, 0.0)
        if f"layer{si + 1}" in want:
            out[f"layer{si + 1}"] = x
    return out


def torch_available() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def forward_torch(net: Network, x: np.ndarray, layers: list[str]) -> dict[str, np.ndarray]:
    """The same features with PyTorch (CPU): same folded weights, same layers."""
    import torch
    import torch.nn.functional as F

    want = set(layers)
    for ly in layers:
        net._check_layer(ly)

    def conv(t, c: Conv):
        if c.same:
            tp, bt, lf, rt = _same_pads(t.shape[-2], t.shape[-1], c)
            t = F.pad(t, [lf, rt, tp, bt])
        return F.conv2d(
            t,
            torch.from_numpy(c.w),
            torch.from_numpy(c.b),
            stride=c.stride,
            padding=0 if c.same else c.pad,
            groups=c.w.shape[0] if c.depthwise else 1,
        )

    out: dict[str, np.ndarray] = {}
    with torch.inference_mode():
        t = torch.from_numpy(np.ascontiguousarray(x))[None]
        if net.family == "vgg":
            k = 0
            for L in net.layers:
                if isinstance(L, str):
                    t = F.max_pool2d(t, 2, 2)
                    k += 1
                    if f"pool{k}" in want:
                        out[f"pool{k}"] = t[0].numpy().copy()
                    if len(out) == len(want):
                        break
                else:
                    t = F.relu(conv(t, L))
            return out
        if net.family == "efficientnet":
            t = F.relu6(conv(t, net.stem))
            for si, stage in enumerate(net.stages):
                for blk in stage:
                    y = F.relu6(conv(t, blk.expand)) if blk.expand is not None else t
                    y = conv(F.relu6(conv(y, blk.depthwise)), blk.project)
                    t = y + t if blk.skip else y
                if f"stage{si + 1}" in want:
                    out[f"stage{si + 1}"] = t[0].numpy().copy()
                if len(out) == len(want):
                    return out
            out["head"] = F.relu6(conv(t, net.head))[0].numpy().copy()
            return out
        t = F.relu(conv(t, net.stem))
        t = F.max_pool2d(t, 3, 2, 1)
        if "pool" in want:
            out["pool"] = t[0].numpy().copy()
        for si, stage in enumerate(net.stages):
            if len(out) == len(want):
                break
            for blk in stage:
                idn = conv(t, blk.down) if blk.down is not None else t
                y = t
                for j, c in enumerate(blk.convs):
                    y = conv(y, c)
                    if j < len(blk.convs) - 1:
                        y = F.relu(y)
                t = F.relu(y + idn)
            if f"layer{si + 1}" in want:
                out[f"layer{si + 1}"] = t[0].numpy().copy()
    return out


def forward(
    net: Network, image: np.ndarray, layers: list[str], *, engine: str = "auto", normalize: bool = True
) -> dict[str, np.ndarray]:
    """Feature maps at ``layers`` of an image (bands, rows, cols) in 0–1.

    engine : "numpy", "torch" or "auto" (torch when installed, else numpy)
    """
    x = prepare_input(image, normalize, net.mean, net.std)
    if engine not in ("auto", "numpy", "torch"):
        raise ConfigError(f"engine must be auto, numpy or torch, got {engine!r}")
    if engine == "torch" or (engine == "auto" and torch_available()):
        if not torch_available():
            raise ConfigError("engine 'torch' needs PyTorch: pip install 'geocd[cnn]' (or use engine numpy)")
        return forward_torch(net, x, layers)
    return forward_np(net, x, layers)


def random_state_dict(backbone: str, seed: int = 0, widths: list | None = None) -> dict[str, np.ndarray]:
    """He-initialised weights with torchvision's names for ``backbone`` (tests, the random-init rows).

    widths : VGG only, a layer list like :data:`VGG_CFGS` (numbers and "M") for a small network
    """
    rng = np.random.default_rng(seed)
    sd: dict[str, np.ndarray] = {}

    def he(o, i, k):
        return (rng.standard_normal((o, i, k, k)) * math.sqrt(2.0 / (i * k * k))).astype(np.float32)

    def bn(prefix, n):
        sd[f"{prefix}.weight"] = (1 + 0.1 * rng.standard_normal(n)).astype(np.float32)
        sd[f"{prefix}.bias"] = (0.1 * rng.standard_normal(n)).astype(np.float32)
        sd[f"{prefix}.running_mean"] = (0.1 * rng.standard_normal(n)).astype(np.float32)
        sd[f"{prefix}.running_var"] = (1 + 0.1 * rng.random(n)).astype(np.float32)

    bb = backbone.lower()
    if bb in EFFNET_LITE_CFGS:
        sd["_conv_stem.weight"] = he(32, 3, 3)
        bn("_bn0", 32)
        for _si, i, k, _stride, e, c_in, mid, cout in _lite_blocks(bb):
            p = f"_blocks.{i}"
            if e != 1:
                sd[f"{p}._expand_conv.weight"] = he(mid, c_in, 1)
                bn(f"{p}._bn0", mid)
            sd[f"{p}._depthwise_conv.weight"] = he(mid, 1, k)
            bn(f"{p}._bn1", mid)
            sd[f"{p}._project_conv.weight"] = he(cout, mid, 1)
            bn(f"{p}._bn2", cout)
        sd["_conv_head.weight"] = he(1280, cout, 1)
        bn("_bn1", 1280)
        return sd
    if bb.startswith("vgg"):
        isbn = bb.endswith("_bn")
        cfg = widths or VGG_CFGS[bb[:-3] if isbn else bb]
        i, cin = 0, 3
        for x in cfg:
            if x == "M":
                i += 1
                continue
            sd[f"features.{i}.weight"] = he(x, cin, 3)
            sd[f"features.{i}.bias"] = (0.01 * rng.standard_normal(x)).astype(np.float32)
            if isbn:
                bn(f"features.{i + 1}", x)
            i += 3 if isbn else 2
            cin = x
        return sd
    if bb not in RESNET_CFGS and not widths:
        raise ConfigError(f"random_state_dict knows {', '.join([*VGG_CFGS, *RESNET_CFGS, *EFFNET_LITE_CFGS])}")
    kind, blocks = RESNET_CFGS.get(bb, ("basic", [1, 1]))
    base = int(widths[0]) if widths else 64
    if widths and len(widths) > 1:
        blocks = [int(b) for b in widths[1:]]
    sd["conv1.weight"] = he(base, 3, 7)
    bn("bn1", base)
    cin = base
    exp = 4 if kind == "bottleneck" else 1
    for si, nb in enumerate(blocks):
        planes = base * 2**si
        for bi in range(nb):
            p = f"layer{si + 1}.{bi}"
            stride = 2 if (si > 0 and bi == 0) else 1
            if kind == "basic":
                sd[f"{p}.conv1.weight"] = he(planes, cin, 3)
                sd[f"{p}.conv2.weight"] = he(planes, planes, 3)
                n = 2
            else:
                sd[f"{p}.conv1.weight"] = he(planes, cin, 1)
                sd[f"{p}.conv2.weight"] = he(planes, planes, 3)
                sd[f"{p}.conv3.weight"] = he(planes * exp, planes, 1)
                n = 3
            for j in range(1, n + 1):
                bn(f"{p}.bn{j}", sd[f"{p}.conv{j}.weight"].shape[0])
            cout = planes * exp
            if stride != 1 or cin != cout:
                sd[f"{p}.downsample.0.weight"] = he(cout, cin, 1)
                bn(f"{p}.downsample.1", cout)
            cin = cout
    return sd
