"""What ``pws finetune`` takes (:class:`FinetuneOptions`) and returns (:class:`FinetuneResult`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from ..bridge.config import PwsConfig
from ..core.errors import require
from ..replay.progress_log import DEFAULT_INTERVAL_S

MODES = ("classifier", "denoiser")
TARGETS = ("soft", "hard")
DEFAULT_MODE = "classifier"   # measured on the demo (docs/finetune.md): see pws_ros.finetune

LogFn = Callable[[str, str], None]   # (level "info" | "warn", message)


@dataclass
class FinetuneOptions:
    """Everything one tuning run needs (the command line fills it; tests build it directly).

    ``config`` supplies the imaging (``imaging``, ``render_factor``, ``border``, ``background``,
    ``render_width``/``render_height``), the motion ``axes`` and their ``radius.<axis>``, the input
    topics and the stamp matching, exactly as ``pws replay`` reads them. ``sigma`` None: the config's.
    """

    bags: list[Path]
    model: Path | None
    out: Path
    config: PwsConfig = field(default_factory=PwsConfig)
    sigma: float | None = None
    mode: str = DEFAULT_MODE          # classifier: fine-tune it; denoiser: train a denoiser before the frozen classifier
    targets: str = "soft"             # the teacher's soft probabilities (KL) or its top class (cross-entropy)
    use_truth: bool = True            # ground-truth labels (/pws/ground_truth) replace the teacher's where present
    holdout: float = 0.2              # the last part of each recording, by time, never trained on
    holdout_clips: list[str] | None = None   # instead: the clips (ground truth ``clip``, globs) held out whole
    new_head: bool = False            # a new linear head for the recordings' label set on the model's outputs
    backbone: str | None = None       # or this backbone (efficientnet_lite0, small_cnn; implies new_head)
    input_size: tuple[int, int] | None = None   # new head: (H, W) of its input (default: the model's, else 120x160)
    noise_warmup: int = 0             # epochs over which the noise rises linearly from 0 to sigma
    consistency: float = 0.0          # weight of the consistency term (KL of two noisy copies to their mean)
    clean_share: float = 0.0          # share of each batch trained without noise (the base classifier on clean frames)
    augment: bool = False             # random colour gains on the drawn pixels, shifts and scales (see Trainer.augment)
    views: int = 4                    # renders at random motions within the radii, per frame (besides alpha = 0)
    stride: int = 1                   # use every stride-th input frame
    max_frames: int | None = None     # per recording, after the stride
    epochs: int = 5
    batch_size: int = 32
    lr: float | None = None           # None: 5e-5 (classifier), 1e-4 (denoiser)
    weight_decay: float = 0.0
    mse_weight: float = 1.0           # denoiser: weight of the MSE to the clean frame beside the classifier's KL
    denoiser_channels: int = 32
    denoiser_depth: int = 5
    init_denoiser: Path | None = None # denoiser: start from this TorchScript denoiser (else a new one, the identity at first)
    eval_samples: int = 100           # noise samples per held-out frame in the report
    seed: int = 0
    device: str = "cpu"
    topics: dict[str, str] = field(default_factory=dict)   # cloud, depth, color, info, depth_info, truth overrides
    classes: Path | None = None
    work_dir: Path | None = None      # None: <out>.work beside the output
    resume: bool = False
    overwrite: bool = False
    checkpoint_every_s: float = 60.0  # and at the end of every epoch, and on SIGINT/SIGTERM
    keep_work: bool = False           # keep the frame cache and checkpoint after a finished run
    quiet: bool = False
    progress: bool | None = None      # None: a bar on a terminal, else log lines; False: none
    progress_interval_s: float = DEFAULT_INTERVAL_S
    log: LogFn | None = None
    on_step: Callable[[int], None] | None = None   # called after every finished training step (tests)

    @property
    def learning_rate(self) -> float:
        if self.lr is not None:
            return float(self.lr)
        if self.backbone == "small_cnn":
            return 3e-3    # from scratch, batch norm: measured on the gestures (docs/real_task.md)
        if self.fresh_head:
            return 1e-4    # gestures, EfficientNet-Lite0: 1e-3 stayed at chance (loss 2.31 after 4 epochs), 1e-4 learns
        return 5e-5 if self.mode == "classifier" else 1e-4

    @property
    def fresh_head(self) -> bool:
        """A new head for the label set is trained (supervised: every frame needs a label)."""
        return bool(self.new_head or self.backbone)

    def noise_sigma(self) -> float:
        return float(self.sigma if self.sigma is not None else self.config.sigma)

    def check(self) -> None:
        """PwsError for values no run can use (one line naming the option)."""
        s = self.noise_sigma()
        require(math.isfinite(s) and s > 0, f"--sigma must be a positive number, got {s:g}")
        require(self.mode in MODES, f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        require(self.targets in TARGETS, f"--targets must be one of {', '.join(TARGETS)}, got {self.targets!r}")
        require(math.isfinite(self.holdout) and 0.0 < self.holdout < 1.0, f"--holdout must lie strictly between 0 and 1, got {self.holdout:g}")
        require(self.views >= 0, f"--views must be >= 0, got {self.views}")
        require(self.stride >= 1, f"--stride must be >= 1, got {self.stride}")
        require(self.max_frames is None or self.max_frames >= 1, f"--max-frames must be >= 1, got {self.max_frames}")
        require(self.epochs >= 1, f"--epochs must be >= 1, got {self.epochs}")
        require(self.batch_size >= 1, f"--batch-size must be >= 1, got {self.batch_size}")
        require(math.isfinite(self.learning_rate) and self.learning_rate > 0, f"--lr must be positive, got {self.learning_rate:g}")
        require(math.isfinite(self.weight_decay) and self.weight_decay >= 0, f"--weight-decay must be >= 0, got {self.weight_decay:g}")
        require(math.isfinite(self.mse_weight) and self.mse_weight >= 0, f"--mse-weight must be >= 0, got {self.mse_weight:g}")
        require(self.denoiser_channels >= 1 and self.denoiser_depth >= 2, "the denoiser needs >= 1 channel and a depth >= 2")
        require(self.eval_samples >= 1, f"--eval-samples must be >= 1, got {self.eval_samples}")
        require(math.isfinite(self.checkpoint_every_s) and self.checkpoint_every_s >= 0,
                f"--checkpoint-every must be >= 0 seconds, got {self.checkpoint_every_s:g}")
        require(len(self.bags) >= 1, "give at least one recording")
        require(self.model is not None or self.backbone, "give --model (a model file) or --backbone")
        require(not (self.model is not None and self.backbone), "give --model or --backbone, not both")
        require(not self.fresh_head or self.mode == "classifier", "a new head is trained with --mode classifier")
        require(not self.fresh_head or self.use_truth, "a new head learns from the labels: drop --no-truth")
        require(math.isfinite(self.consistency) and self.consistency >= 0, f"--consistency must be >= 0, got {self.consistency:g}")
        require(math.isfinite(self.clean_share) and 0.0 <= self.clean_share < 1.0,
                f"--clean-share must lie in [0, 1), got {self.clean_share:g}")
        require(self.noise_warmup >= 0, f"--noise-warmup must be >= 0 epochs, got {self.noise_warmup}")
        require(self.holdout_clips is None or len(self.holdout_clips) > 0, "--holdout-clips needs at least one clip pattern")
        require(self.init_denoiser is None or self.mode == "denoiser", "--init-denoiser needs --mode denoiser")
        require(self.init_denoiser is None or Path(self.init_denoiser).is_file(), f"denoiser file not found: {self.init_denoiser}")
        require(0 <= int(self.seed) < 2**63, f"--seed must be a non-negative integer, got {self.seed}")

    def resolved_work_dir(self) -> Path:
        return Path(self.work_dir) if self.work_dir is not None else Path(str(self.out) + ".work")

    def report_path(self) -> Path:
        out = Path(self.out)
        return out.with_name(out.stem + ".finetune.json")

    def denoiser_path(self) -> Path:
        out = Path(self.out)
        return out.with_name(out.stem + ".denoiser.pt")


@dataclass
class FinetuneResult:
    """What a run produced: the model file, the report (also written as JSON), the exit code."""

    model_path: Path | None
    report_path: Path | None
    report: dict[str, Any]
    exit_code: int = 0
    message: str = ""
    interrupted: str = ""
    extra_files: list[Path] = field(default_factory=list)


__all__ = ["DEFAULT_MODE", "FinetuneOptions", "FinetuneResult", "MODES", "TARGETS"]
