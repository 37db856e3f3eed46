"""The student, its loss and the training loop with checkpoints (see :mod:`pws_ros.finetune`).

Every random draw of step ``s`` comes from seeds derived from (seed, s): the batch from the epoch's
permutation, the noise, dropout (torch's global generator, re-seeded per step). A run resumed from
the checkpoint of step ``s`` therefore continues exactly as the uninterrupted run would: same seed,
identical weights.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.errors import PwsError, require
from ..core.model import quiet_jit
from .cache import RecordingCache, derive

CHECKPOINT_FORMAT = "pws_ros-finetune-checkpoint-1"
_PERM, _NOISE, _STEP, _NOISE2, _AUG, _CLEAN = 11, 12, 13, 14, 15, 16   # seed tags
AUG_GAIN, AUG_LEVEL, AUG_SHIFT, AUG_SCALE = 0.4, 0.2, 12.0, 0.4   # --augment: see Trainer.augment (shift, scale: docs/real_task.md setting 15)


def load_script(path: Path, device: torch.device) -> Any:
    """A fresh copy of the TorchScript model (the teacher stays untouched)."""
    try:
        with quiet_jit():
            return torch.jit.load(str(path), map_location=device)
    except Exception as exc:  # load_model accepted it already; this is unexpected
        raise PwsError(f"model {path} cannot be loaded for training: {str(exc).splitlines()[0][:160]}") from None


class DenoisedClassifier(nn.Module):
    """``classifier(denoiser(x))``: the model file of the denoiser mode (one file for ``--model``)."""

    def __init__(self, denoiser: nn.Module, classifier: nn.Module):
        super().__init__()
        self.denoiser = denoiser
        self.classifier = classifier

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.classifier(self.denoiser(x))


class Student:
    """What is trained: the classifier itself (``classifier`` mode) or a denoiser before the frozen
    classifier (``denoiser`` mode). ``trainable`` holds the parameters and the checkpointed state."""

    def __init__(self, mode: str, model_path: Path, device: torch.device, *, channels: int = 32, depth: int = 5,
                 init_denoiser: Path | None = None):
        self.mode = mode
        self.device = device
        self.classifier = load_script(model_path, device)
        if mode == "classifier":
            self.trainable: nn.Module = self.classifier
            for p in self.classifier.parameters():
                p.requires_grad_(True)
        else:
            from ..sim.train import Denoiser

            self.classifier.eval()
            for p in self.classifier.parameters():
                p.requires_grad_(False)
            if init_denoiser is not None:
                self.trainable = load_script(Path(init_denoiser), device)
            else:
                den = Denoiser(channels, depth)
                last = den.body[-1]
                nn.init.zeros_(last.weight)   # the identity at step 0: training starts from the classifier alone
                nn.init.zeros_(last.bias)
                self.trainable = den.to(device)
        params = [p for p in self.trainable.parameters() if p.requires_grad]
        require(len(params) > 0, f"model {model_path} has no trainable parameters (was it frozen or traced without them?)")
        self.params = params

    def train(self) -> None:
        self.trainable.train()
        if self.mode == "denoiser":
            self.classifier.eval()

    def eval(self) -> None:
        self.trainable.eval()
        self.classifier.eval()

    def denoise(self, x: torch.Tensor) -> torch.Tensor:
        return self.trainable(x) if self.mode == "denoiser" else x

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.classifier(self.denoise(x))

    def export_module(self) -> nn.Module:
        """The module the output model file holds."""
        self.eval()
        if self.mode == "classifier":
            return self.classifier
        return DenoisedClassifier(self.trainable, self.classifier).eval()

    def num_params(self) -> int:
        return int(sum(p.numel() for p in self.params))


class TrainSet:
    """The training items (frame, view) of the train split of every recording, read from the cache."""

    def __init__(self, caches: list[RecordingCache], splits: list[range], use_truth: bool):
        self.caches = caches
        rows = [(ci, fi) for ci, (c, s) in enumerate(zip(caches, splits)) for fi in s]
        require(len(rows) > 0, "no frame to train on")
        self.frames = np.asarray(rows, dtype=np.int64)          # (F, 2): cache index, frame index
        self.views = int(caches[0].views.shape[1])
        self.use_truth = use_truth

    def __len__(self) -> int:
        return len(self.frames) * self.views

    def batch(self, items: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Clean images (B, 3, H, W) float32, teacher probabilities (B, C), teacher top class (B,),
        ground-truth label (B,) (-1 where none or not used)."""
        f, v = items // self.views, items % self.views
        imgs, probs, tops, truth = [], [], [], []
        for fi, vi in zip(f.tolist(), v.tolist()):
            ci, k = self.frames[fi]
            c = self.caches[ci]
            imgs.append(np.asarray(c.views[k, vi]))
            probs.append(c.probs[k])
            tops.append(c.frames[k]["teacher"])
            truth.append(c.frames[k]["truth_label"] if self.use_truth else -1)
        x = torch.from_numpy(np.stack(imgs).transpose(0, 3, 1, 2).astype(np.float32) / 255.0)
        return (x, torch.from_numpy(np.stack(probs)), torch.as_tensor(tops, dtype=torch.long),
                torch.as_tensor(truth, dtype=torch.long))


def lr_at(step: int, total: int, base: float) -> float:
    """Linear warm-up over the first min(100, 5%) steps, then cosine decay to 0 at ``total``."""
    warm = max(1, min(100, total // 20))
    if step < warm:
        return base * (step + 1) / warm
    t = (step - warm) / max(1, total - warm)
    return base * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t)))


def atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        torch.save(obj, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class Trainer:
    """The loop: ``run(start_step)``; ``state()`` / ``load(state)`` for checkpoints."""

    def __init__(self, student: Student, data: TrainSet, *, sigma: float, epochs: int, batch_size: int, lr: float,
                 weight_decay: float, targets: str, mse_weight: float, seed: int, device: torch.device,
                 consistency: float = 0.0, noise_warmup: int = 0, clean_share: float = 0.0, augment: bool = False,
                 background: float = 0.5):
        self.student = student
        self.data = data
        self.sigma = float(sigma)
        self.batch_size = int(batch_size)
        self.steps_per_epoch = int(math.ceil(len(data) / self.batch_size))
        self.total = int(epochs) * self.steps_per_epoch
        self.base_lr = float(lr)
        self.targets = targets
        self.mse_weight = float(mse_weight)
        self.consistency = float(consistency)
        self.warm_steps = int(noise_warmup) * self.steps_per_epoch   # sigma rises linearly from 0 over these steps
        self.clean_share = float(clean_share)
        self.augment_on = bool(augment)
        self.background = float(background)
        self.seed = int(seed)
        self.device = device
        self.opt = torch.optim.AdamW(student.params, lr=self.base_lr, weight_decay=float(weight_decay))
        self.step = 0
        self.history: list[dict] = []     # per epoch: mean loss, agreement of the noisy batch with the target
        self._acc = [0.0, 0, 0]           # loss sum, items, agreeing items of the epoch so far

    def items(self, step: int) -> np.ndarray:
        epoch, k = divmod(step, self.steps_per_epoch)
        g = torch.Generator().manual_seed(derive(self.seed, _PERM, epoch))
        perm = torch.randperm(len(self.data), generator=g).numpy()
        return perm[k * self.batch_size:(k + 1) * self.batch_size]

    def loss(self, x: torch.Tensor, probs: torch.Tensor, tops: torch.Tensor, truth: torch.Tensor,
             noise: torch.Tensor, noise2: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The target loss on ``x + noise`` (KL / cross-entropy to the teacher, cross-entropy to the label
        where there is one); with ``noise2`` (consistency regularisation, as the paper trains its
        classifiers) also on ``x + noise2``, plus ``consistency`` x the mean KL of each copy's
        prediction to the copies' mean prediction."""
        copies = 1 if noise2 is None else 2
        noisy = x + noise if noise2 is None else torch.cat([x + noise, x + noise2])
        den = self.student.denoise(noisy)
        logits = self.student.classifier(den)
        logp = F.log_softmax(logits.float(), dim=1)
        probs, tops, truth = probs.repeat(copies, 1), tops.repeat(copies), truth.repeat(copies)
        if self.targets == "soft":
            per = F.kl_div(logp, probs, reduction="none").sum(dim=1)
        else:
            per = F.nll_loss(logp, tops, reduction="none")
        has = truth >= 0
        if bool(has.any()):
            per = torch.where(has, F.nll_loss(logp, truth.clamp_min(0), reduction="none"), per)
        loss = per.mean()
        if copies == 2 and self.consistency > 0:
            lp = logp.view(2, len(x), -1)
            mean = lp.exp().mean(dim=0).clamp_min(1e-12)
            kl = (mean[None] * (mean.log()[None] - lp)).sum(dim=2).mean()
            loss = loss + self.consistency * kl
        if self.student.mode == "denoiser" and self.mse_weight > 0:
            loss = loss + self.mse_weight * F.mse_loss(den, x.repeat(copies, 1, 1, 1))
        target = torch.where(has, truth, tops)
        return loss, (logits.argmax(dim=1) == target)

    def augment(self, x: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        """``--augment``, per image (draws from ``g``): the drawn pixels (those not equal to the background in
        every channel, to the cache's 1/255) times a gain uniform in 1 +- AUG_GAIN per channel and 1 +- AUG_LEVEL
        overall, clipped to [0, 1]; then the image scaled by 1 +- AUG_SCALE about its centre and shifted by up to
        AUG_SHIFT input pixels each way (bilinear; what comes in from outside is the background)."""
        b, _, h, w = x.shape
        dev = x.device

        def u(*shape: int) -> torch.Tensor:
            return torch.rand(shape, generator=g, device=dev, dtype=x.dtype) * 2 - 1

        drawn = ((x - round(self.background * 255) / 255).abs() > 0.5 / 255).any(dim=1, keepdim=True)
        gain = (1 + AUG_GAIN * u(b, 3, 1, 1)) * (1 + AUG_LEVEL * u(b, 1, 1, 1))
        x = torch.where(drawn, (x * gain).clamp(0, 1), x)
        theta = torch.zeros(b, 2, 3, device=dev, dtype=x.dtype)
        scale = 1 + AUG_SCALE * u(b)
        theta[:, 0, 0] = scale
        theta[:, 1, 1] = scale
        theta[:, 0, 2] = AUG_SHIFT * 2 / w * u(b)
        theta[:, 1, 2] = AUG_SHIFT * 2 / h * u(b)
        grid = F.affine_grid(theta, list(x.shape), align_corners=False)
        return F.grid_sample(x - self.background, grid, align_corners=False, padding_mode="zeros") + self.background

    def one_step(self) -> float:
        s = self.step
        for group in self.opt.param_groups:
            group["lr"] = lr_at(s, self.total, self.base_lr)
        x, probs, tops, truth = self.data.batch(self.items(s))
        dev = self.device
        x, probs, tops, truth = x.to(dev), probs.to(dev), tops.to(dev), truth.to(dev)
        g = torch.Generator(device=dev).manual_seed(derive(self.seed, _NOISE, s))
        sigma = self.sigma * (min(1.0, (s + 1) / self.warm_steps) if self.warm_steps > 0 else 1.0)
        if self.augment_on:
            x = self.augment(x, torch.Generator(device=dev).manual_seed(derive(self.seed, _AUG, s)))
        scale: torch.Tensor | float = sigma
        if self.clean_share > 0:   # these images without noise: the base classifier learns the clean frames too
            gc = torch.Generator(device=dev).manual_seed(derive(self.seed, _CLEAN, s))
            clean = torch.rand((len(x), 1, 1, 1), generator=gc, device=dev, dtype=x.dtype) < self.clean_share
            scale = sigma * (~clean).to(x.dtype)
        noise = torch.randn(x.shape, generator=g, device=dev, dtype=x.dtype) * scale
        noise2 = None
        if self.consistency > 0:
            g2 = torch.Generator(device=dev).manual_seed(derive(self.seed, _NOISE2, s))
            noise2 = torch.randn(x.shape, generator=g2, device=dev, dtype=x.dtype) * scale
        torch.manual_seed(derive(self.seed, _STEP, s))   # dropout and any other draw inside the model
        self.student.train()
        loss, agree = self.loss(x, probs, tops, truth, noise, noise2)
        require(bool(torch.isfinite(loss.detach())), f"training diverged at step {s} (loss {float(loss.detach())}): lower --lr")
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        value = float(loss.detach())
        self._acc[0] += value * len(agree)
        self._acc[1] += len(agree)
        self._acc[2] += int(agree.sum())
        self.step = s + 1
        if self.step % self.steps_per_epoch == 0 or self.step == self.total:
            self.history.append({"epoch": (self.step - 1) // self.steps_per_epoch + 1, "step": self.step,
                                 "loss": self._acc[0] / max(1, self._acc[1]),
                                 "noisy_agreement": self._acc[2] / max(1, self._acc[1])})
            self._acc = [0.0, 0, 0]
        return value

    @property
    def epoch_end(self) -> bool:
        return self.step % self.steps_per_epoch == 0

    def state(self, key: str, elapsed_s: float) -> dict:
        return {"format": CHECKPOINT_FORMAT, "key": key, "step": self.step, "total": self.total,
                "trainable": self.student.trainable.state_dict(), "optimizer": self.opt.state_dict(),
                "history": list(self.history), "acc": list(self._acc), "elapsed_s": float(elapsed_s)}

    def load(self, state: dict) -> None:
        self.student.trainable.load_state_dict(state["trainable"])
        self.opt.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        self.history = list(state["history"])
        self._acc = [float(state["acc"][0]), int(state["acc"][1]), int(state["acc"][2])]


def load_checkpoint(path: Path, key: str, device: torch.device) -> dict | None:
    """The checkpoint at ``path`` if it belongs to this run (same ``key``: same settings and frames)."""
    if not path.exists():
        return None
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:
        raise PwsError(f"checkpoint {path} cannot be read ({str(exc).splitlines()[0][:120]}): remove the work folder "
                       "or run without --resume (with --overwrite)") from None
    require(isinstance(state, dict) and state.get("format") == CHECKPOINT_FORMAT, f"{path} is not a pws finetune checkpoint")
    require(state.get("key") == key, f"checkpoint {path} was made with other settings: run without --resume (with --overwrite) "
                                     "to start over, or resume with the settings it was made with")
    return state


__all__ = ["AUG_GAIN", "AUG_LEVEL", "AUG_SCALE", "AUG_SHIFT", "DenoisedClassifier", "Student", "TrainSet", "Trainer", "atomic_save", "load_checkpoint", "load_script", "lr_at",
           "quiet_jit"]
