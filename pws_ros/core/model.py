"""The model contract: a TorchScript classifier of noisy images, its class names and metadata.

A model file is a TorchScript archive whose ``forward`` maps float images ``(B, 3, H, W)`` with
values in ``[0, 1]`` (the smoothing noise already added, so values may leave that range) to logits
``(B, C)``. Any normalisation (mean/std) lives *inside* the model. :func:`save_model` also stores
an extra file ``pws.json`` in the archive::

    {"format": "pws_ros-model-1", "class_names": [...], "input_height": H, "input_width": W,
     "sigma": s, ...}

and writes a sidecar ``<stem>.classes.txt`` (one class name per line) next to the model.

Class names are taken from, in order: an explicit ``classes`` argument (a path or a list of names),
``<stem>.classes.txt`` beside the model, ``classes.txt`` in the same folder, ``pws.json``; a sidecar
wins over ``pws.json``. If none exists they are ``class_0, class_1, ...`` from the output size.

:func:`export_model` (bring your own model) turns a user's PyTorch classifier (an ``nn.Module``, with its
input normalisation, class names and training noise sigma) into such a file (``pws export-model`` on
the command line).

A denoiser (:func:`load_denoiser`) is a TorchScript module ``(B, 3, H, W) -> (B, 3, H, W)``.
"""
from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import torch

from .errors import PwsError, require
from .render import resolve_device

META_FILE = "pws.json"
META_FORMAT = "pws_ros-model-1"
DRY_RUN_SIZE = (32, 32)


@contextmanager
def quiet_jit() -> Iterator[None]:
    """TorchScript still works in torch 2.x but warns that it is deprecated on every call: this silences
    those warnings (here and in :mod:`pws_ros.finetune`)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.jit.*")
        warnings.filterwarnings("ignore", message=r".*torch\.jit.*deprecated.*")
        yield


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _shape_str(shape: Sequence[int]) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ")"


@dataclass
class LoadedModel:
    """A classifier ready for inference (eval mode, on ``device``).

    Call it with ``(B, 3, H, W)`` float images to get logits ``(B, C)``; the output is checked
    (2-D, ``C == num_classes``, finite). ``input_size`` is ``(H, W)`` when the model declares it.
    ``class_names`` may be empty until the first call when the output size could not be learned
    at load time (a model that rejected the dry-run input); ``num_classes`` is then 0.
    """

    module: Any
    class_names: list[str]
    input_size: tuple[int, int] | None
    path: str
    meta: dict = field(default_factory=dict)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def class_name(self, index: int) -> str:
        index = int(index)
        if 0 <= index < len(self.class_names):
            return self.class_names[index]
        return f"class_{index}"

    def check_input_size(self, height: int, width: int, what: str = "input") -> None:
        """PwsError unless ``height x width`` matches the declared input size (if any)."""
        if self.input_size is not None and (int(height), int(width)) != tuple(self.input_size):
            h, w = self.input_size
            raise PwsError(f"model {self.path} expects {w}x{h} (WxH) images but the {what} is {int(width)}x{int(height)}")

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        require(isinstance(x, torch.Tensor), f"model {self.path}: input must be a torch tensor, got {type(x).__name__}")
        require(x.ndim == 4 and x.shape[1] == 3, f"model {self.path}: input must have shape (B, 3, H, W), got {_shape_str(x.shape)}")
        self.check_input_size(x.shape[2], x.shape[3])
        if x.device != self.device:
            x = x.to(self.device)
        with torch.no_grad():
            try:
                out = self.module(x)
            except PwsError:
                raise
            except Exception as exc:  # TorchScript errors are long; keep one line
                raise PwsError(f"model {self.path} failed on input {_shape_str(x.shape)}: {_first_line(exc)}") from None
        if not isinstance(out, torch.Tensor):
            raise PwsError(f"model {self.path} returned {type(out).__name__}, expected a (B, C) tensor of logits")
        if not self.class_names and out.ndim == 2 and out.shape[0] == x.shape[0] and out.shape[1] >= 1:
            # output size learned at the first call
            self.class_names = [f"class_{i}" for i in range(int(out.shape[1]))]
        if out.ndim != 2 or out.shape[0] != x.shape[0] or out.shape[1] != self.num_classes:
            raise PwsError(f"model {self.path} returned shape {_shape_str(out.shape)}, expected (B, C) = ({x.shape[0]}, {self.num_classes})")
        if not bool(torch.isfinite(out).all()):
            raise PwsError(f"model {self.path} returned NaN or infinite logits")
        return out


# ---- class names ---------------------------------------------------------------------------

def read_class_file(path: str | Path) -> list[str]:
    """Class names, one per line (surrounding blanks stripped; blank lines ignored)."""
    path = Path(path)
    require(path.is_file(), f"class file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise PwsError(f"cannot read class file {path}: {_first_line(exc)}") from None
    names = [line.strip() for line in text.splitlines() if line.strip()]
    require(len(names) > 0, f"class file {path} lists no class names")
    _check_names(names, f"class file {path}")
    return names


def _check_names(names: Sequence[str], source: str) -> list[str]:
    out = []
    seen: set[str] = set()
    for name in names:
        require(isinstance(name, str), f"{source}: class names must be strings, got {type(name).__name__}")
        name = name.strip()
        require(name != "", f"{source}: empty class name")
        require("\n" not in name and "\r" not in name, f"{source}: class name {name!r} contains a line break")
        require(name not in seen, f"{source}: class name {name!r} appears twice")
        seen.add(name)
        out.append(name)
    return out


def sidecar_path(model_path: str | Path) -> Path:
    """``<stem>.classes.txt`` beside the model."""
    model_path = Path(model_path)
    return model_path.with_name(model_path.stem + ".classes.txt")


def find_class_file(model_path: str | Path) -> Path | None:
    """``<stem>.classes.txt`` beside the model, else ``classes.txt`` in its folder, else None."""
    model_path = Path(model_path)
    for cand in (sidecar_path(model_path), model_path.with_name("classes.txt")):
        if cand.is_file():
            return cand
    return None


# ---- loading -------------------------------------------------------------------------------

def _load_script(path: Path, device: torch.device, what: str) -> tuple[Any, dict]:
    require(path.exists(), f"{what} file not found: {path}")
    require(path.is_file(), f"{what} path is not a file: {path}")
    extra = {META_FILE: ""}
    try:
        with quiet_jit():
            module = torch.jit.load(str(path), map_location=device, _extra_files=extra)
    except Exception as exc:
        raise PwsError(f"{what} {path} is not a TorchScript archive ({_first_line(exc)[:120]}); "
                       f"save it with torch.jit.script(m).save(path) or pws_ros.core.model.save_model") from None
    raw = extra.get(META_FILE) or b""
    meta: dict = {}
    if raw:
        try:
            meta = json.loads(raw.decode("utf-8") if isinstance(raw, bytes) else raw)
        except (ValueError, UnicodeDecodeError) as exc:
            raise PwsError(f"{what} {path}: its {META_FILE} is not valid JSON ({_first_line(exc)})") from None
        require(isinstance(meta, dict), f"{what} {path}: its {META_FILE} must hold a JSON object")
    module.eval()
    return module, meta


def _meta_input_size(meta: dict, source: str) -> tuple[int, int] | None:
    h, w = meta.get("input_height"), meta.get("input_width")
    if h is None and w is None:
        return None
    try:
        hi, wi = int(h), int(w)
    except (TypeError, ValueError):
        raise PwsError(f"{source}: input_height/input_width must be integers, got {h!r}/{w!r}") from None
    require(hi > 0 and wi > 0 and hi == h and wi == w, f"{source}: input size must be positive integers, got {h!r}x{w!r}")
    return (hi, wi)


def load_model(path: str | Path, classes: str | Path | Sequence[str] | None = None,
               device: str | torch.device | None = "cpu") -> LoadedModel:
    """Load a TorchScript classifier, its class names and metadata, and check it on a dry run.

    ``classes``: an explicit class file or a list of names (else the sidecar / ``classes.txt`` /
    ``pws.json`` / ``class_i``). The dry run feeds zeros of the declared input size (or
    ``(1, 3, 32, 32)`` when none is declared, skipped if the model rejects that size) and checks
    the output is ``(1, C)`` with ``C`` equal to the number of class names.
    """
    path = Path(path)
    dev = resolve_device(device)
    module, meta = _load_script(path, dev, "model")
    source = f"model {path}"
    input_size = _meta_input_size(meta, source)

    names: list[str] | None = None
    names_source = ""
    if classes is not None:
        if isinstance(classes, (str, Path)):
            names, names_source = read_class_file(classes), f"class file {classes}"
        else:
            names = _check_names(list(classes), "class names")
            require(len(names) > 0, "class names: the list is empty")
            names_source = "the given class names"
    else:
        found = find_class_file(path)
        if found is not None:
            names, names_source = read_class_file(found), f"class file {found}"
        elif meta.get("class_names") is not None:
            meta_names = meta["class_names"]
            require(isinstance(meta_names, list) and len(meta_names) > 0, f"{source}: {META_FILE} class_names must be a non-empty list")
            names, names_source = _check_names(meta_names, f"{source} ({META_FILE})"), f"{META_FILE} in {path}"

    # dry run
    out_classes: int | None = None
    size = input_size or DRY_RUN_SIZE
    x = torch.zeros((1, 3) + tuple(size), dtype=torch.float32, device=dev)
    try:
        with torch.no_grad(), quiet_jit():
            out = module(x)
    except Exception as exc:
        if input_size is not None:
            raise PwsError(f"{source} failed on a dry run with zeros of shape {_shape_str(x.shape)}: {_first_line(exc)}") from None
        out = None  # unknown input size and 32x32 rejected: validate at the first call
    if out is not None:
        if not isinstance(out, torch.Tensor) or out.ndim != 2 or out.shape[0] != 1 or out.shape[1] < 1:
            shape = _shape_str(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
            raise PwsError(f"{source} returned shape {shape} on a dry run with {_shape_str(x.shape)}, expected (B, C) = (1, C)")
        out_classes = int(out.shape[1])

    if names is not None and out_classes is not None:
        require(len(names) == out_classes,
                f"{names_source} has {len(names)} class names but model {path} outputs {out_classes} classes")
    if names is None:
        names = [f"class_{i}" for i in range(out_classes)] if out_classes is not None else []
    return LoadedModel(module=module, class_names=list(names), input_size=input_size, path=str(path), meta=meta, device=dev)


# ---- saving --------------------------------------------------------------------------------

def _module_device(module: torch.nn.Module) -> torch.device:
    for t in list(module.parameters()) + list(module.buffers()):
        return t.device
    return torch.device("cpu")


def save_model(module: torch.nn.Module, path: str | Path, class_names: Sequence[str],
               input_size: tuple[int, int] | None = (32, 32), meta: dict | None = None) -> Path:
    """Script (or, failing that, trace) ``module`` and save it with ``pws.json`` and a class sidecar.

    ``input_size`` is ``(H, W)`` of the images the model takes; ``meta`` adds JSON-serialisable
    fields (e.g. ``{"sigma": 0.5}``) to ``pws.json``. The module is checked on zeros of that size
    (output must be ``(1, len(class_names))``). Returns the model path.
    """
    path = Path(path)
    names = _check_names(list(class_names), "save_model class_names")
    require(len(names) > 0, "save_model: class_names is empty")
    if input_size is not None:
        require(len(tuple(input_size)) == 2, f"save_model: input_size must be (H, W), got {input_size!r}")
        h, w = (int(v) for v in input_size)
        require(h > 0 and w > 0 and (h, w) == tuple(input_size), f"save_model: input_size must be positive integers, got {input_size!r}")
        input_size = (h, w)
    meta = dict(meta or {})
    info: dict[str, Any] = {**meta, "format": META_FORMAT, "class_names": names}
    if input_size is not None:
        info["input_height"], info["input_width"] = input_size
    try:
        payload = json.dumps(info, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise PwsError(f"save_model: meta is not JSON-serialisable ({_first_line(exc)})") from None

    if isinstance(module, torch.nn.Module):
        module.eval()
    example = torch.zeros((1, 3) + tuple(input_size or DRY_RUN_SIZE), dtype=torch.float32, device=_module_device(module))
    with quiet_jit():
        if isinstance(module, torch.jit.ScriptModule):
            scripted = module
        else:
            try:
                scripted = torch.jit.script(module)
            except Exception as script_exc:
                try:
                    with torch.no_grad():
                        scripted = torch.jit.trace(module, example, check_trace=False)
                except Exception as trace_exc:
                    raise PwsError(f"save_model: cannot script ({_first_line(script_exc)[:100]}) nor trace "
                                   f"({_first_line(trace_exc)[:100]}) the module") from None
        scripted.eval()
        try:
            with torch.no_grad():
                out = scripted(example)
        except Exception as exc:
            raise PwsError(f"save_model: the module fails on zeros of shape {_shape_str(example.shape)}: {_first_line(exc)}") from None
        require(isinstance(out, torch.Tensor) and out.ndim == 2 and tuple(out.shape) == (1, len(names)),
                f"save_model: the module returned shape {_shape_str(getattr(out, 'shape', ()))} for one image, "
                f"expected (1, {len(names)}) to match the class names")
        path.parent.mkdir(parents=True, exist_ok=True)
        scripted.save(str(path), _extra_files={META_FILE: payload})
    sidecar_path(path).write_text("\n".join(names) + "\n", encoding="utf-8")
    return path


# ---- bring your own model (pws export-model) ---------------------------------------------

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


# ---- denoiser ------------------------------------------------------------------------------

@dataclass
class LoadedDenoiser:
    """A TorchScript denoiser ``(B, 3, H, W) -> (B, 3, H, W)``; the shape is checked at each call."""

    module: Any
    path: str
    meta: dict = field(default_factory=dict)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if x.device != self.device:
            x = x.to(self.device)
        with torch.no_grad():
            try:
                out = self.module(x)
            except Exception as exc:
                raise PwsError(f"denoiser {self.path} failed on input {_shape_str(x.shape)}: {_first_line(exc)}") from None
        require(isinstance(out, torch.Tensor) and tuple(out.shape) == tuple(x.shape),
                f"denoiser {self.path} returned shape {_shape_str(getattr(out, 'shape', ()))}, expected {_shape_str(x.shape)}")
        return out


def load_denoiser(path: str | Path, device: str | torch.device | None = "cpu") -> LoadedDenoiser:
    """Load a TorchScript denoiser; dry-run on ``(1, 3, 32, 32)`` zeros when it accepts that size."""
    path = Path(path)
    dev = resolve_device(device)
    module, meta = _load_script(path, dev, "denoiser")
    den = LoadedDenoiser(module=module, path=str(path), meta=meta, device=dev)
    size = _meta_input_size(meta, f"denoiser {path}") or DRY_RUN_SIZE
    x = torch.zeros((1, 3) + tuple(size), dtype=torch.float32, device=dev)
    try:
        with torch.no_grad(), quiet_jit():
            out = module(x)
    except Exception:
        return den  # size rejected: checked at the first call
    require(isinstance(out, torch.Tensor) and tuple(out.shape) == tuple(x.shape),
            f"denoiser {path} returned shape {_shape_str(getattr(out, 'shape', ()))} for input {_shape_str(x.shape)}; it must keep the shape")
    return den


__all__ = ["IMAGENET_MEAN", "IMAGENET_STD", "META_FILE", "LoadedDenoiser", "LoadedModel", "Normalized", "export_model",
           "find_class_file", "load_denoiser", "load_model", "quiet_jit", "read_class_file", "save_model", "sidecar_path"]
