"""Training the demo models: a tiny seeded run of the full recipe, the model contract of what it
writes, the smoothed-accuracy evaluation against a brute-force count, and the CLI."""
from __future__ import annotations

import argparse
import json
import warnings

import numpy as np
import pytest
import torch

from pws_ros.core.errors import PwsError
from pws_ros.core.model import load_denoiser, load_model
from pws_ros.sim import CLASS_NAMES, NUM_CLASSES
from pws_ros.sim.dataset import TRAIN_SEED_BASE, heldout_set, moved_view, training_set
from pws_ros.sim.train import Denoiser, SmallCNN, build_models, count_params, evaluate, train_classifier


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    out = tmp_path_factory.mktemp("models")
    report = build_models(out, preset="tiny", seed=0, workers=1, cache_dir="", log=None)
    return out, report


def test_tiny_recipe_writes_loadable_models(tiny_models):
    out, report = tiny_models
    for sigma in ("0.25", "0.50"):
        m = load_model(out / f"classifier_sigma{sigma}.pt")
        assert m.class_names == list(CLASS_NAMES)
        assert m.input_size == (18, 32)
        assert m.meta["sigma"] == pytest.approx(float(sigma))
        logits = m(torch.rand(3, 3, 18, 32))
        assert logits.shape == (3, NUM_CLASSES)
        assert (out / f"classifier_sigma{sigma}.classes.txt").read_text().split() == list(CLASS_NAMES)
    assert (out / "classes.txt").read_text().split() == list(CLASS_NAMES)
    d = load_denoiser(out / "denoiser_sigma0.50.pt")
    assert d.meta["kind"] == "denoiser" and d.meta["sigma"] == 0.5
    assert d(torch.rand(2, 3, 18, 32)).shape == (2, 3, 18, 32)
    saved = json.loads((out / "training_report.json").read_text())
    assert saved["heldout"] == report["heldout"]
    for key in ("classifier_sigma0.25", "classifier_sigma0.50"):
        r = report["heldout"][key]
        assert 0.0 <= r["clean_accuracy"] <= 1.0 and 0.0 <= r["smoothed_accuracy"] <= 1.0
        assert r["num_images"] == NUM_CLASSES


def test_training_is_deterministic():
    X, Y = training_set(6, 1, seed=3, width=24, height=16, move_prob=0.5, cache_dir=None)
    X2, Y2 = training_set(6, 1, seed=3, width=24, height=16, move_prob=0.5, cache_dir=None)
    assert np.array_equal(X, X2) and np.array_equal(Y, Y2)
    base = TRAIN_SEED_BASE + 3 * 100_000
    assert list(Y) == [(base + i) % NUM_CLASSES for i in range(6)]  # consecutive training seeds cycle classes
    a = train_classifier(X, Y, 0.5, epochs=1, batch_size=4, seed=1)
    b = train_classifier(X, Y, 0.5, epochs=1, batch_size=4, seed=1)
    for pa, pb in zip(a.state_dict().values(), b.state_dict().values()):
        assert torch.equal(pa, pb)


def test_dataset_cache_round_trip(tmp_path):
    X, Y = heldout_set(1, views=(0, 3), width=24, height=16, cache_dir=tmp_path)
    assert X.shape == (2 * NUM_CLASSES, 16, 24, 3) and X.dtype == np.uint8
    assert len(list(tmp_path.glob("heldout_*.npz"))) == 1
    X2, Y2 = heldout_set(1, views=(0, 3), width=24, height=16, cache_dir=tmp_path)
    assert np.array_equal(X, X2) and np.array_equal(Y, Y2)
    assert list(Y[::2]) == list(range(NUM_CLASSES))


def test_moved_view_at_zero_motion_is_the_view():
    from pws_ros.sim import default_intrinsics, make_scene, raycast, view_pose

    scene = make_scene(1)
    intr = default_intrinsics(40, 24)
    rgb, depth = raycast(scene, view_pose(scene, 2), intr)
    assert np.array_equal(moved_view(rgb, depth, intr, "tx", 0.0), rgb)
    shifted = moved_view(rgb, depth, intr, "tx", 0.05)
    assert not np.array_equal(shifted, rgb)


class _ConstNet(torch.nn.Module):
    """Class = 0 if mean(red) < t else 1 (a deterministic brute-force reference)."""

    def forward(self, x):
        m = x[:, 0].mean(dim=(1, 2))
        out = torch.zeros(x.shape[0], NUM_CLASSES)
        out[:, 0] = 0.5 - m
        out[:, 1] = m - 0.5
        return out


def test_evaluate_matches_brute_force_vote():
    rng = np.random.default_rng(0)
    imgs = rng.integers(0, 256, size=(6, 4, 5, 3), dtype=np.uint8)
    imgs[:3, ..., 0] = 10   # clearly class 0
    imgs[3:, ..., 0] = 250  # clearly class 1
    labels = np.array([0, 0, 1, 1, 1, 0])
    r = evaluate(_ConstNet(), imgs, labels, sigma=0.1, num_samples=9, batch_size=4, seed=0)
    # clean: predictions 0,0,0,1,1,1 -> correct at 0,1,3,4 ; smoothed identical (noise is small vs margin)
    assert r["clean_accuracy"] == pytest.approx(4 / 6)
    assert r["smoothed_accuracy"] == pytest.approx(4 / 6)
    # a denoiser that maps everything to zeros makes every prediction class 0
    r0 = evaluate(_ConstNet(), imgs, labels, sigma=0.1, num_samples=5, denoiser=lambda x: torch.zeros_like(x))
    assert r0["clean_accuracy"] == pytest.approx(3 / 6) and r0["smoothed_accuracy"] == pytest.approx(3 / 6)


def test_models_are_small_and_size_agnostic():
    m = SmallCNN().eval()
    assert 50_000 <= count_params(m) <= 200_000
    assert m(torch.rand(2, 3, 90, 160)).shape == (2, NUM_CLASSES)
    d = Denoiser().eval()
    for h, w in ((90, 160), (45, 81), (17, 33)):
        x = torch.rand(1, 3, h, w)
        assert d(x).shape == x.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        scripted = torch.jit.script(d)
    assert scripted(torch.rand(1, 3, 45, 81)).shape == (1, 3, 45, 81)


def _cli(argv):
    from pws_ros.commands import train

    parser = argparse.ArgumentParser(prog="pws")
    train.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_train_classifier_and_denoiser(tmp_path):
    assert _cli(["train", "classifier", "--preset", "tiny", "--out", str(tmp_path / "c.pt"), "--sigma", "0.25", "--workers", "1", "--cache-dir", ""]) == 0
    m = load_model(tmp_path / "c.pt")
    assert m.meta["sigma"] == 0.25 and m.class_names == list(CLASS_NAMES)
    assert _cli(["train", "denoiser", "--preset", "tiny", "--out", str(tmp_path / "d.pt"), "--workers", "1", "--cache-dir", ""]) == 0
    assert load_denoiser(tmp_path / "d.pt").meta["sigma"] == 0.5
    with pytest.raises(PwsError, match="sigma"):
        _cli(["train", "classifier", "--preset", "tiny", "--out", str(tmp_path / "e.pt"), "--sigma", "-1", "--cache-dir", ""])
