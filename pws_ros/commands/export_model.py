"""``pws export-model``: turn your own PyTorch classifier into the model file the certifier loads."""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

from ..core.errors import PwsError, require
from .common import add_output_args, image_size
from . import SUMMARIES

DESCRIPTION = """\
Turn your own PyTorch image classifier into the file that `pws certify`, `pws replay` and the ROS 2
nodes load: a TorchScript archive with its metadata (input size, normalisation, class names, training
noise sigma) and a <stem>.classes.txt beside it (pws_ros.core.model.export_model does the same from
Python). The shipped bags/models are demo models for the procedural world; real images need yours.

SOURCE is one of:
  path/to/file.py:NAME   NAME in that Python file
  package.module:NAME    NAME in an importable module
  model.pt               a TorchScript archive (metadata is added; normalisation wrapped around it)
where NAME is an nn.Module instance, an nn.Module class, or a function returning an nn.Module; classes
and functions are called without arguments. --weights then loads a state dict into it.

The module maps (B, 3, H, W) RGB images to logits (B, C). With --mean/--std (or --imagenet) it
expects (x - mean) / std with x in [0, 1], and that normalisation is put inside the exported model
(the certifier feeds x in [0, 1] plus Gaussian noise). Randomized smoothing certifies a classifier
trained with that noise: give its sigma with --sigma; one trained without noise mostly abstains."""

EPILOG = """\
example:
  pws export-model my_net.py:build --weights my_net.pth --input-size 224x224 --classes classes.txt \\
      --imagenet --sigma 0.25 --out models/my_net.pt
  pws certify --cloud view/cloud.npz --camera view/camera.yaml --model models/my_net.pt --axis tz --radius 0.01

exit status: 0 written, 2 bad input (one line naming the problem)."""


def _floats(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected one number or three separated by commas, got {text!r}") from None


def register(subparsers) -> None:
    p = subparsers.add_parser("export-model", help=SUMMARIES["export-model"],
                              description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("source", metavar="SOURCE", help="file.py:NAME, package.module:NAME or a TorchScript .pt (see above)")
    p.add_argument("--out", required=True, metavar="MODEL.pt", help="model file to write (and MODEL.classes.txt beside it)")
    p.add_argument("--input-size", required=True, type=image_size, metavar="HxW", help="image size the model takes, e.g. 224x224")
    p.add_argument("--classes", required=True, metavar="FILE|A,B,...",
                   help="class names: a file with one per line, or a comma-separated list (one per model output)")
    p.add_argument("--weights", metavar="STATE.pth", help="a state dict to load into the module (torch.save(model.state_dict()); "
                                                          "a checkpoint dict with 'state_dict' or 'model_state_dict' works too)")
    p.add_argument("--mean", type=_floats, metavar="M|R,G,B", help="input normalisation mean of the module (images in [0, 1])")
    p.add_argument("--std", type=_floats, metavar="S|R,G,B", help="input normalisation std of the module")
    p.add_argument("--imagenet", action="store_true", help="the ImageNet normalisation (mean 0.485,0.456,0.406, std 0.229,0.224,0.225)")
    p.add_argument("--sigma", type=float, metavar="S", help="Gaussian noise sigma the model was trained with (images in [0, 1]), if known")
    add_output_args(p, "print what was written as JSON")
    p.set_defaults(func=run)


def _load_source(source: str) -> Any:
    """The object a SOURCE names (see DESCRIPTION)."""
    path = Path(source)
    if path.suffix in (".pt", ".pth", ".ts", ".zip") and ":" not in path.name:
        require(path.is_file(), f"model file not found: {path}")
        from ..core.model import _load_script

        import torch

        module, _meta = _load_script(path, torch.device("cpu"), "model")
        return module
    target, sep, name = source.rpartition(":")
    require(bool(sep) and bool(target) and bool(name), f"SOURCE {source!r}: expected file.py:NAME, package.module:NAME or a TorchScript .pt")
    if target.endswith(".py"):
        file = Path(target)
        require(file.is_file(), f"SOURCE {source!r}: file {file} not found")
        spec = importlib.util.spec_from_file_location(f"pws_user_model_{abs(hash(str(file.resolve())))}", file)
        mod = importlib.util.module_from_spec(spec)
        sys.path.insert(0, str(file.resolve().parent))   # the file's own imports of its neighbours
        try:
            spec.loader.exec_module(mod)
        except Exception as exc:
            raise PwsError(f"SOURCE {source!r}: running {file} failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}") from None
        finally:
            sys.path.remove(str(file.resolve().parent))
    else:
        try:
            mod = importlib.import_module(target)
        except Exception as exc:
            raise PwsError(f"SOURCE {source!r}: cannot import {target}: {type(exc).__name__}: {exc}") from None
    require(hasattr(mod, name), f"SOURCE {source!r}: {target} has no {name!r}")
    return getattr(mod, name)


def build_module(source: str, weights: str | None = None) -> Any:
    """The ``nn.Module`` of SOURCE, with ``weights`` (a state dict file) loaded into it."""
    import torch

    obj = _load_source(source)
    if not isinstance(obj, torch.nn.Module) and callable(obj):
        try:
            obj = obj()
        except Exception as exc:
            raise PwsError(f"SOURCE {source!r}: calling it without arguments failed: {type(exc).__name__}: {exc}") from None
    require(isinstance(obj, torch.nn.Module), f"SOURCE {source!r} gives a {type(obj).__name__}, not a torch.nn.Module")
    if weights:
        wpath = Path(weights)
        require(wpath.is_file(), f"--weights file not found: {wpath}")
        try:
            state = torch.load(str(wpath), map_location="cpu", weights_only=True)
        except Exception as exc:
            raise PwsError(f"--weights {wpath} is not a state dict saved with torch.save ({str(exc).splitlines()[0][:160]})") from None
        if isinstance(state, dict):
            for key in ("state_dict", "model_state_dict"):
                if isinstance(state.get(key), dict):
                    state = state[key]
                    break
        require(isinstance(state, dict), f"--weights {wpath} holds a {type(state).__name__}, not a state dict")
        try:
            obj.load_state_dict(state, strict=True)
        except Exception as exc:
            raise PwsError(f"--weights {wpath} does not fit the module: {' '.join(str(exc).split())[:240]}") from None
    return obj


def run(args: argparse.Namespace) -> int:
    from ..core.model import IMAGENET_MEAN, IMAGENET_STD, export_model
    from ..core.model import load_model

    require(not (args.imagenet and (args.mean or args.std)), "--imagenet and --mean/--std exclude each other")
    mean, std = (IMAGENET_MEAN, IMAGENET_STD) if args.imagenet else (args.mean, args.std)
    require((mean is None) == (std is None), "give both --mean and --std (or --imagenet), or neither")
    classes: Any = args.classes
    if not Path(classes).is_file():
        require("," in classes or not Path(classes).suffix, f"--classes {classes}: no such file (a list needs commas: a,b,c)")
        classes = [c.strip() for c in classes.split(",")]
    module = build_module(args.source, args.weights)
    out = export_model(module, args.out, args.input_size, classes, mean=mean, std=std, sigma=args.sigma)
    loaded = load_model(out)
    info = {"model": str(out), "classes_file": str(out.with_name(out.stem + ".classes.txt")), "num_classes": loaded.num_classes,
            "input_size": list(loaded.input_size or ()), "normalization": loaded.meta.get("normalization"),
            "sigma": loaded.meta.get("sigma")}
    if args.json:
        print(json.dumps(info, indent=1))
    else:
        h, w = args.input_size
        norm = info["normalization"]
        print(f"wrote {out} and {info['classes_file']}: {loaded.num_classes} classes, input {w}x{h} (WxH), "
              + (f"normalisation mean {norm['mean']} std {norm['std']} inside" if norm else "takes images in [0, 1]")
              + (f", trained with sigma {info['sigma']:g}" if info["sigma"] is not None else ", training sigma unknown"))
    return 0
