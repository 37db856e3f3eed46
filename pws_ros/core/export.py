"""Bring your own model: turn a PyTorch classifier (an ``nn.Module``, with its input normalisation,
class names and training noise sigma) into a model file of the contract of :mod:`pws_ros.core.model`
(``pws export-model`` on the command line)."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from .errors import require
from .model import _module_device, read_class_file, save_model


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _channel_triple(value: float | Sequence[float], what: str) -> list[float]:
    vals = [float(value)] * 3 if isinstance(value, (int, float)) else [float(v) for v in value]
    require(len(vals) in (1, 3), f"export_model: {what} must be one number or three (R, G, B), got {len(vals)}")
    vals = vals * 3 if len(vals) == 1 else vals
    require(all(v == v and abs(v) != float("inf") for v in vals), f"export_model: {what} must be finite, got {vals}")
    return vals


class Normalized(torch.nn.Module):
    """``module((x - mean) / std)`` per RGB channel: puts a classifier's input normalisation inside the
    model, as the contract wants (the certifier feeds images in [0, 1] plus noise)."""

    def __init__(self, module: torch.nn.Module, mean: Sequence[float], std: Sequence[float]):
        super().__init__()
        self.module = module
        device = _module_device(module)
        self.register_buffer("mean", torch.tensor(list(mean), dtype=torch.float32, device=device).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(list(std), dtype=torch.float32, device=device).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.module((x - self.mean) / self.std)


def export_model(module: torch.nn.Module, path: str | Path, input_size: tuple[int, int],
                 class_names: Sequence[str] | str | Path, *, mean: float | Sequence[float] | None = None,
                 std: float | Sequence[float] | None = None, sigma: float | None = None, meta: dict | None = None) -> Path:
    """Turn a user's PyTorch classifier into the model file :func:`load_model` (and the nodes) load.

    ``module`` maps ``(B, 3, H, W)`` RGB images to logits ``(B, C)``; with ``mean`` / ``std`` it expects
    images normalised as ``(x - mean) / std`` with ``x`` in [0, 1] (e.g. :data:`IMAGENET_MEAN`,
    :data:`IMAGENET_STD`) and the normalisation is put inside the exported model; without them it
    takes ``x`` in [0, 1] as it is. ``input_size`` is ``(H, W)``: the certifier renders frames at that
    size. ``class_names`` is a list (one per output) or a class file (one per line). ``sigma`` is the
    Gaussian noise the model was trained with, if known (a replay or node using another sigma warns).
    Writes ``path`` (TorchScript, scripted or else traced, with ``pws.json``) and ``<stem>.classes.txt``;
    returns ``path``. A classifier not trained with noise still certifies, but mostly abstains.
    """
    require(isinstance(module, torch.nn.Module), f"export_model: expected a torch.nn.Module, got {type(module).__name__}")
    require(isinstance(input_size, (tuple, list)) and len(input_size) == 2, f"export_model: input_size must be (H, W), got {input_size!r}")
    names = read_class_file(class_names) if isinstance(class_names, (str, Path)) else list(class_names)
    require((mean is None) == (std is None), "export_model: give both mean and std, or neither")
    info = dict(meta or {})
    if mean is not None:
        m, sd = _channel_triple(mean, "mean"), _channel_triple(std, "std")
        require(all(v > 0 for v in sd), f"export_model: std must be positive, got {sd}")
        module = Normalized(module, m, sd)
        info["normalization"] = {"mean": m, "std": sd}
    if sigma is not None:
        require(isinstance(sigma, (int, float)) and float(sigma) >= 0 and float(sigma) != float("inf"),
                f"export_model: sigma must be a finite number >= 0, got {sigma!r}")
        info["sigma"] = float(sigma)
    info.setdefault("exported_by", "pws_ros.core.model.export_model")
    return save_model(module, path, names, input_size=tuple(input_size), meta=info)


__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "Normalized", "export_model"]
