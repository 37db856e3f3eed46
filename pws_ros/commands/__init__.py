"""Subcommands of ``pws``: each module has ``register(subparsers)`` and ``run(args) -> int``.

:data:`SUMMARIES` is the one line ``pws --help`` lists for each (in that order): the CLI reads it here
and imports a command's module (which may import torch) only when that command runs or shows its help."""

SUMMARIES = {
    "plan": "compute the camera-motion partitions of a cloud",
    "render": "render the frames of a plan (z-buffer) and the per-segment bounds",
    "certify": "certify a classifier's smoothed prediction against camera motion",
    "audit": "self-audit: check a plan's per-segment bounds on densely re-rendered poses",
    "replay": "certify a rosbag2 recording offline; write the results as a bag + report",
    "ceiling": "what a recording allows: the ceiling (a never-changing classifier) next to your model",
    "bench": "measure PwS against CMS side by side and check the paper's claims",
    "sim": "procedural RGB-D world: record bags, export views",
    "train": "train the demo classifier / denoiser on the procedural world",
    "export-model": "turn your own PyTorch classifier into a model file for the certifier",
    "finetune": "make a model robust to the smoothing noise on your own recordings (no labels needed)",
    "import": "RGB-D frames, TUM sequences, labels -> recordings pws replay / finetune read",
}


def module_name(command: str) -> str:
    """The module of ``pws COMMAND`` (``export-model`` -> ``export_model``, ``import`` -> ``importing``: a keyword)."""
    return "importing" if command == "import" else command.replace("-", "_")
