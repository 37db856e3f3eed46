"""Train the demo classifier (Gaussian-noise augmentation) and denoiser on the procedural world.

``build_models(out_dir, preset="full")`` is the seeded, reproducible recipe behind the shipped
``bags/models`` files (``pws train all --out bags/models``):

1. generate training views (random poses around training scenes, some re-rendered after a small
   camera motion) and held-out canonical views of scenes ``0 ...``; cached as .npz;
2. train :class:`SmallCNN` with noise sigma 0.5 from scratch, then fine-tune a copy with sigma 0.25;
3. train the :class:`Denoiser` (DnCNN-like, residual) for sigma 0.5 on random crops (MSE);
4. report clean accuracy and smoothed accuracy (majority vote of noisy samples) on held-out views,
   and whether the denoiser helps; write everything with :func:`pws_ros.core.model.save_model`.
"""
from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.errors import require
from ..core.model import META_FILE, META_FORMAT, save_model
from .dataset import default_cache_dir, heldout_set, training_set
from .objects import CLASS_NAMES, NUM_CLASSES


# ------------------------------------------------------------------------------------------------
# models
# ------------------------------------------------------------------------------------------------
class SmallCNN(nn.Module):
    """2x2 average pooling, then strided convolutions and global average pooling; input
    ``(B, 3, H, W)`` in [0, 1] (+ noise), normalised inside. About 165k parameters and 8 MMAC per
    160x90 image; any input size >= 16x16 works."""

    def __init__(self, num_classes: int = NUM_CLASSES, width: int = 1, mean=(0.5, 0.5, 0.5), std=(0.25, 0.25, 0.25)):
        super().__init__()
        c = [24 * width, 48 * width, 96 * width, 128 * width]
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))

        def block(i, o, k, s):
            return nn.Sequential(nn.Conv2d(i, o, k, s, k // 2, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True))

        self.pool = nn.AvgPool2d(2, ceil_mode=True)
        self.features = nn.Sequential(block(3, c[0], 5, 2), block(c[0], c[1], 3, 2), block(c[1], c[2], 3, 2), block(c[2], c[3], 3, 2))
        self.drop = nn.Dropout(0.1)
        self.fc = nn.Linear(c[3], num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.pool((x - self.mean) / self.std)
        x = self.features(x)
        x = x.mean(dim=(2, 3))
        return self.fc(self.drop(x))


class Denoiser(nn.Module):
    """DnCNN-like residual denoiser at half resolution: pixel-unshuffle by 2 (odd sizes are
    padded), ``depth`` 3x3 conv+ReLU layers of ``channels``, predict the noise, pixel-shuffle back,
    subtract. Input and output ``(B, 3, H, W)``."""

    def __init__(self, channels: int = 32, depth: int = 4):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(12, channels, 3, 1, 1), nn.ReLU(inplace=True)]
        for _ in range(depth - 2):
            layers += [nn.Conv2d(channels, channels, 3, 1, 1), nn.ReLU(inplace=True)]
        layers.append(nn.Conv2d(channels, 12, 3, 1, 1))
        self.body = nn.Sequential(*layers)
        self.down = nn.PixelUnshuffle(2)
        self.up = nn.PixelShuffle(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[2], x.shape[3]
        ph, pw = h % 2, w % 2
        y = F.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x
        noise = self.up(self.body(self.down(y - 0.5)))
        return (y - noise)[:, :, :h, :w]


def count_params(m: nn.Module) -> int:
    return int(sum(p.numel() for p in m.parameters()))


# ------------------------------------------------------------------------------------------------
# training loops
# ------------------------------------------------------------------------------------------------
def _to_tensor(images: np.ndarray) -> torch.Tensor:
    """uint8 (N, H, W, 3) -> uint8 (N, 3, H, W) tensor (converted to float per batch)."""
    return torch.from_numpy(np.ascontiguousarray(np.asarray(images, dtype=np.uint8).transpose(0, 3, 1, 2)))


def _batches(n: int, batch_size: int, gen: torch.Generator, shuffle: bool = True):
    order = torch.randperm(n, generator=gen) if shuffle else torch.arange(n)
    for s in range(0, n, batch_size):
        yield order[s : s + batch_size]


def _augment(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random horizontal flip and mild brightness / per-channel gain jitter (x float in [0, 1])."""
    b = x.shape[0]
    flip = torch.rand(b, generator=gen) < 0.5
    x = torch.where(flip.view(-1, 1, 1, 1), x.flip(3), x)
    gain = 1.0 + 0.12 * (torch.rand(b, 1, 1, 1, generator=gen) - 0.5) + 0.06 * (torch.rand(b, 3, 1, 1, generator=gen) - 0.5)
    return (x * gain).clamp_(0.0, 1.0)


def train_classifier(images: np.ndarray, labels: np.ndarray, sigma: float, *, epochs: int = 10, batch_size: int = 128,
                     lr: float = 3e-3, seed: int = 0, init: nn.Module | None = None, width: int = 1,
                     log: Callable[[str], None] | None = None) -> SmallCNN:
    """Train (or fine-tune ``init``) with Gaussian noise of ``sigma`` added to every image."""
    require(len(images) == len(labels) and len(images) > 0, "training set is empty or mislabelled")
    require(sigma >= 0, f"sigma must be >= 0, got {sigma}")
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    X = _to_tensor(images)
    Y = torch.as_tensor(np.asarray(labels, dtype=np.int64))
    if init is None:
        xf = X[: min(len(X), 2000)].float() / 255.0
        mean = tuple(float(v) for v in xf.mean(dim=(0, 2, 3)))
        std = tuple(float(v) for v in xf.std(dim=(0, 2, 3)).clamp_min(0.05))
        model = SmallCNN(NUM_CLASSES, width=width, mean=mean, std=std)
    else:
        import copy

        model = copy.deepcopy(init)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    steps = max(1, epochs * math.ceil(len(X) / batch_size))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.15 if init is None else 0.05)
    model.train()
    for ep in range(epochs):
        t0, tot, correct, loss_sum = time.time(), 0, 0, 0.0
        for idx in _batches(len(X), batch_size, gen):
            x = _augment(X[idx].float() / 255.0, gen)
            x = x + sigma * torch.randn(x.shape, generator=gen)
            y = Y[idx]
            out = model(x)
            loss = F.cross_entropy(out, y, label_smoothing=0.05)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            tot += len(idx)
            correct += int((out.argmax(1) == y).sum())
            loss_sum += float(loss.detach()) * len(idx)
        if log:
            log(f"  classifier sigma={sigma:g} epoch {ep + 1}/{epochs}: loss {loss_sum / tot:.3f}, noisy train acc {correct / tot:.3f} ({time.time() - t0:.0f}s)")
    model.eval()
    return model


def train_denoiser(images: np.ndarray, sigma: float, *, epochs: int = 3, batch_size: int = 64, crop: tuple[int, int] = (48, 64),
                   lr: float = 2e-3, seed: int = 0, channels: int = 32, depth: int = 4,
                   log: Callable[[str], None] | None = None) -> Denoiser:
    """MSE training on random crops of noisy/clean pairs."""
    require(len(images) > 0, "training set is empty")
    torch.manual_seed(seed + 1)
    gen = torch.Generator().manual_seed(seed + 1)
    X = _to_tensor(images)
    H, W = X.shape[2], X.shape[3]
    ch, cw = min(crop[0], H) // 2 * 2, min(crop[1], W) // 2 * 2
    model = Denoiser(channels, depth)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    steps = max(1, epochs * math.ceil(len(X) / batch_size))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.1)
    model.train()
    for ep in range(epochs):
        t0, loss_sum, tot = time.time(), 0.0, 0
        for idx in _batches(len(X), batch_size, gen):
            r = int(torch.randint(0, H - ch + 1, (1,), generator=gen))
            c = int(torch.randint(0, W - cw + 1, (1,), generator=gen))
            x = _augment(X[idx, :, r : r + ch, c : c + cw].float() / 255.0, gen)
            noisy = x + sigma * torch.randn(x.shape, generator=gen)
            loss = F.mse_loss(model(noisy), x)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            loss_sum += float(loss.detach()) * len(idx)
            tot += len(idx)
        if log:
            log(f"  denoiser sigma={sigma:g} epoch {ep + 1}/{epochs}: mse {loss_sum / tot:.4f} (noisy input mse {sigma**2:.4f}) ({time.time() - t0:.0f}s)")
    model.eval()
    return model


# ------------------------------------------------------------------------------------------------
# evaluation
# ------------------------------------------------------------------------------------------------
@torch.no_grad()
def evaluate(model, images: np.ndarray, labels: np.ndarray, sigma: float, *, num_samples: int = 100, batch_size: int = 500,
             denoiser=None, seed: int = 0) -> dict:
    """Clean accuracy and smoothed accuracy (majority vote of ``num_samples`` noisy copies,
    optionally denoised first; ties go to the lower class index) on ``images``, and the mean and
    minimum fraction of noisy copies voting for the true class (what p_A, hence a certificate,
    rests on)."""
    gen = torch.Generator().manual_seed(seed)
    X = _to_tensor(images)
    Y = np.asarray(labels, dtype=np.int64)
    clean_pred, smooth_pred, true_vote = [], [], []
    for i in range(len(X)):
        x = X[i : i + 1].float() / 255.0
        clean_pred.append(int(model(denoiser(x) if denoiser is not None else x).argmax(1)))
        counts = torch.zeros(NUM_CLASSES, dtype=torch.long)
        left = num_samples
        while left > 0:
            b = min(batch_size, left)
            noisy = x.expand(b, -1, -1, -1) + sigma * torch.randn((b,) + tuple(x.shape[1:]), generator=gen)
            if denoiser is not None:
                noisy = denoiser(noisy)
            pred = model(noisy).argmax(1)
            counts += torch.bincount(pred, minlength=len(counts))[: len(counts)]
            left -= b
        smooth_pred.append(int(counts.argmax()))
        true_vote.append(float(counts[int(Y[i])]) / num_samples)
    clean = np.asarray(clean_pred)
    smooth = np.asarray(smooth_pred)
    return {"clean_accuracy": float((clean == Y).mean()), "smoothed_accuracy": float((smooth == Y).mean()),
            "mean_true_vote": float(np.mean(true_vote)), "min_true_vote": float(np.min(true_vote)),
            "sigma": float(sigma), "num_samples": int(num_samples), "num_images": int(len(Y))}


# ------------------------------------------------------------------------------------------------
# the recipe
# ------------------------------------------------------------------------------------------------
@dataclass
class Preset:
    train_scenes: int
    views_per_scene: int
    width: int
    height: int
    epochs_05: int
    epochs_025: int
    denoiser_epochs: int
    heldout_per_class: int
    heldout_views: tuple
    smooth_samples: int
    denoiser_eval_images: int
    denoiser_eval_samples: int = 50
    move_prob: float = 0.4
    net_width: int = 1
    denoiser_channels: int = 32
    denoiser_depth: int = 4


PRESETS = {
    "full": Preset(train_scenes=2400, views_per_scene=4, width=160, height=90, epochs_05=6, epochs_025=2, denoiser_epochs=2,
                   heldout_per_class=15, heldout_views=(0, 13), smooth_samples=100, denoiser_eval_images=72),
    "tiny": Preset(train_scenes=24, views_per_scene=1, width=32, height=18, epochs_05=1, epochs_025=1, denoiser_epochs=1,
                   heldout_per_class=1, heldout_views=(0,), smooth_samples=4, denoiser_eval_images=6, denoiser_eval_samples=4,
                   denoiser_channels=8, denoiser_depth=3),
}


def save_denoiser(module: nn.Module, path: str | Path, sigma: float, input_size: tuple[int, int] | None, meta: dict | None = None) -> Path:
    """TorchScript denoiser with ``pws.json`` (kind, sigma, input size)."""
    path = Path(path)
    info = {**(meta or {}), "format": META_FORMAT, "kind": "denoiser", "sigma": float(sigma)}
    if input_size is not None:
        info["input_height"], info["input_width"] = int(input_size[0]), int(input_size[1])
    module.eval()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        scripted = torch.jit.script(module)
        path.parent.mkdir(parents=True, exist_ok=True)
        scripted.save(str(path), _extra_files={META_FILE: json.dumps(info)})
    return path


def build_models(out_dir: str | Path, *, preset: str = "full", seed: int = 0, workers: int = 2, cache_dir: str | Path | None = None,
                 threads: int = 2, log: Callable[[str], None] | None = print, skip_denoiser: bool = False) -> dict:
    """Generate data, train and write ``classifier_sigma0.25.pt``, ``classifier_sigma0.50.pt``,
    ``classes.txt``, ``denoiser_sigma0.50.pt`` and ``training_report.json`` into ``out_dir``."""
    require(preset in PRESETS, f"unknown preset {preset!r}: expected one of {', '.join(PRESETS)}")
    p = PRESETS[preset]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, int(threads)))
    cache = default_cache_dir() if cache_dir is None else (None if str(cache_dir) == "" else Path(cache_dir))
    log = log or (lambda s: None)
    t_start = time.time()
    report: dict = {"preset": preset, "preset_params": asdict(p), "seed": seed, "class_names": list(CLASS_NAMES)}

    t0 = time.time()
    Xtr, Ytr = training_set(p.train_scenes, p.views_per_scene, seed=seed, width=p.width, height=p.height, move_prob=p.move_prob,
                            workers=workers, cache_dir=cache)
    Xte, Yte = heldout_set(p.heldout_per_class, p.heldout_views, width=p.width, height=p.height, workers=workers, cache_dir=cache)
    report["data"] = {"train_images": int(len(Xtr)), "heldout_images": int(len(Xte)), "seconds": round(time.time() - t0, 1)}
    log(f"data: {len(Xtr)} training views, {len(Xte)} held-out views ({time.time() - t0:.0f}s)")

    t0 = time.time()
    m05 = train_classifier(Xtr, Ytr, 0.5, epochs=p.epochs_05, seed=seed, width=p.net_width, log=log)
    m025 = train_classifier(Xtr, Ytr, 0.25, epochs=p.epochs_025, seed=seed + 1, init=m05, lr=1e-3, log=log)
    report["classifier_params"] = count_params(m05)
    report["classifier_train_seconds"] = round(time.time() - t0, 1)
    size = (p.height, p.width)
    for sigma, model in ((0.25, m025), (0.5, m05)):
        path = out / f"classifier_sigma{sigma:.2f}.pt"
        save_model(model, path, CLASS_NAMES, input_size=size,
                   meta={"sigma": sigma, "trained_on": "pws_ros.sim procedural world", "preset": preset, "seed": seed})
    (out / "classes.txt").write_text("\n".join(CLASS_NAMES) + "\n", encoding="utf-8")

    evals = {}
    for sigma, model in ((0.25, m025), (0.5, m05)):
        evals[f"classifier_sigma{sigma:.2f}"] = evaluate(model, Xte, Yte, sigma, num_samples=p.smooth_samples, seed=seed)
        log(f"held-out, sigma {sigma}: {evals[f'classifier_sigma{sigma:.2f}']}")
    report["heldout"] = evals

    if not skip_denoiser:
        t0 = time.time()
        den = train_denoiser(Xtr, 0.5, epochs=p.denoiser_epochs, seed=seed, channels=p.denoiser_channels, depth=p.denoiser_depth, log=log)
        save_denoiser(den, out / "denoiser_sigma0.50.pt", 0.5, size, meta={"preset": preset, "seed": seed})
        report["denoiser_params"] = count_params(den)
        report["denoiser_train_seconds"] = round(time.time() - t0, 1)
        k = min(len(Xte), p.denoiser_eval_images)
        sub = np.random.default_rng(seed).permutation(len(Xte))[:k]
        comp = {
            "classifier_sigma0.50": evaluate(m05, Xte[sub], Yte[sub], 0.5, num_samples=p.denoiser_eval_samples, seed=seed + 7),
            "denoiser+classifier_sigma0.50": evaluate(m05, Xte[sub], Yte[sub], 0.5, num_samples=p.denoiser_eval_samples, seed=seed + 7, denoiser=den),
            "denoiser+classifier_sigma0.25": evaluate(m025, Xte[sub], Yte[sub], 0.5, num_samples=p.denoiser_eval_samples, seed=seed + 7, denoiser=den),
        }
        with torch.no_grad():
            x = torch.from_numpy(np.ascontiguousarray(Xte[sub].transpose(0, 3, 1, 2))).float() / 255.0
            g = torch.Generator().manual_seed(seed + 9)
            noisy = x + 0.5 * torch.randn(x.shape, generator=g)
            comp["denoiser_mse"] = float(F.mse_loss(den(noisy), x))
            comp["noisy_mse"] = float(F.mse_loss(noisy, x))
        report["denoiser_comparison_sigma0.50"] = comp
        log(f"denoiser comparison at sigma 0.5: {comp}")
    report["total_seconds"] = round(time.time() - t_start, 1)
    (out / "training_report.json").write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return report


__all__ = ["Denoiser", "PRESETS", "Preset", "SmallCNN", "build_models", "count_params", "evaluate", "save_denoiser",
           "train_classifier", "train_denoiser"]
