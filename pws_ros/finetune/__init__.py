"""Make an exported classifier robust to Gaussian noise of a chosen sigma on your own recordings,
without labels (``pws finetune``), or train a new head for a labelled recording's classes
(:mod:`.heads`: ``--backbone`` / ``--new-head``, cross-entropy to the labels, clips held out whole by
``--holdout-clips``, optional consistency regularisation; docs/real_task.md).

The teacher is the original model on the clean frames; the student learns to give the teacher's
answer on noisy frames (KL to the teacher's probabilities, or cross-entropy to its top class; a
ground-truth label from ``/pws/ground_truth`` replaces the teacher's where present). The frames are
exactly what the certifier feeds the classifier: the reduced alpha = 0 frame of the imaging model
(the engine's ``imaging_for``: crop, render factor, border) and renders of the same one-frame cloud at
random motions within the configured radii, read from the recordings with the replay's own input
path (:mod:`.frames`) and cached on disk (:mod:`.cache`).

Two modes (:mod:`.train`): ``classifier`` (default) fine-tunes the model itself; ``denoiser`` trains a
small residual denoiser (:class:`pws_ros.sim.train.Denoiser`) before the frozen classifier (KL plus
MSE to the clean frame), written as one model file (denoiser + classifier) and as a denoiser file
for ``--denoiser``. The last part of each recording (``holdout``, by time) is never trained on; the
report (:mod:`.evaluate`) measures on it how often the smoothed prediction agrees with the teacher's
clean one, and the p_A distribution, before and after.

Runs are seeded and resumable: the frame cache is appended frame by frame, the training
checkpoint is written atomically (every ``checkpoint_every_s``, at each epoch end and on
SIGINT/SIGTERM), and a resumed run gives the same weights as an uninterrupted one.
"""
from __future__ import annotations

from .options import DEFAULT_MODE, MODES, TARGETS, FinetuneOptions, FinetuneResult
from .run import FinetuneRun, finetune, summary_lines

__all__ = ["DEFAULT_MODE", "MODES", "TARGETS", "FinetuneOptions", "FinetuneResult", "FinetuneRun", "finetune", "summary_lines"]
