"""Bring your own model: a user's PyTorch classifier exported with the documented paths
(pws_ros.core.model.export_model and `pws export-model`), loaded with load_model, and used to certify."""
from __future__ import annotations

import json
import textwrap
import warnings

import numpy as np
import pytest
import torch

from conftest import REPO
from pws_ros.cli import main
from pws_ros.core.camera import CameraIntrinsics
from pws_ros.core.certify import CertifyConfig, certify
from pws_ros.core.cloud import Cloud
from pws_ros.core.errors import PwsError
from pws_ros.core.model import IMAGENET_MEAN, IMAGENET_STD, export_model, load_model
from pws_ros.core.result import STATUS_ERROR

SIZE = (45, 80)   # (H, W): the sample view (160x90) rendered at half resolution
CLASSES = ["ball", "box", "other"]


class UserNet(torch.nn.Module):
    """What a user might have: a small CNN that expects ImageNet-normalised input."""

    def __init__(self, classes: int = 3):
        super().__init__()
        torch.manual_seed(0)
        self.features = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, stride=2), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1))
        self.head = torch.nn.Linear(4, classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(torch.flatten(self.features(x), 1))


def normalised_reference(net: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """The user's net on (x - mean) / std, computed here channel by channel."""
    y = x.clone()
    for c in range(3):
        y[:, c] = (x[:, c] - IMAGENET_MEAN[c]) / IMAGENET_STD[c]
    with torch.no_grad():
        return net(y)


def test_export_load_and_certify_a_frame(tmp_path):
    net = UserNet()
    out = export_model(net, tmp_path / "user.pt", SIZE, CLASSES, mean=IMAGENET_MEAN, std=IMAGENET_STD, sigma=0.25)
    assert (tmp_path / "user.classes.txt").read_text().split() == CLASSES
    model = load_model(out)
    assert model.class_names == CLASSES and model.input_size == SIZE
    assert model.meta["sigma"] == 0.25 and model.meta["normalization"] == {"mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD)}
    x = torch.rand(4, 3, *SIZE)
    torch.testing.assert_close(model(x), normalised_reference(net, x), rtol=1e-5, atol=1e-5)
    # certify a frame of the shipped sample view with it (tiny sample sizes: any status but ERROR)
    cloud = Cloud.load(REPO / "bags" / "sample_view" / "cloud.npz")
    intr = CameraIntrinsics.from_yaml(REPO / "bags" / "sample_view" / "camera.yaml").scaled(SIZE[1], SIZE[0])
    cert = certify(cloud, intr, model, "tz", 0.002, "pws_of", CertifyConfig(sigma=0.25, n0=8, n=16, batch_size=64))
    assert cert.status != STATUS_ERROR, cert.reason
    assert cert.class_name in CLASSES + [""]


def test_export_without_normalisation_and_bad_input(tmp_path):
    net = UserNet(2)
    model = load_model(export_model(net, tmp_path / "plain.pt", SIZE, ["a", "b"]))
    x = torch.rand(2, 3, *SIZE)
    with torch.no_grad():
        torch.testing.assert_close(model(x), net(x))
    assert "sigma" not in model.meta and "normalization" not in model.meta
    with pytest.raises(PwsError, match="class names"):
        export_model(net, tmp_path / "bad.pt", SIZE, ["a", "b", "c"])
    with pytest.raises(PwsError, match="both mean and std"):
        export_model(net, tmp_path / "bad.pt", SIZE, ["a", "b"], mean=0.5)
    with pytest.raises(PwsError, match="std must be positive"):
        export_model(net, tmp_path / "bad.pt", SIZE, ["a", "b"], mean=0.5, std=0.0)
    with pytest.raises(PwsError, match="sigma"):
        export_model(net, tmp_path / "bad.pt", SIZE, ["a", "b"], sigma=-1)


USER_FILE = '''
import torch


class Net(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 5, 3)
        self.fc = torch.nn.Linear(5, 3)

    def forward(self, x):
        return self.fc(self.conv(x).mean(dim=(2, 3)))


def build():
    return Net()
'''


def test_cli_export_model_from_a_python_file_and_weights(tmp_path, capsys):
    src = tmp_path / "user_net.py"
    src.write_text(textwrap.dedent(USER_FILE))
    ns: dict = {}
    exec(compile(src.read_text(), str(src), "exec"), ns)   # the user's net, trained elsewhere: random weights here
    torch.manual_seed(3)
    trained = ns["build"]()
    torch.save({"epoch": 7, "state_dict": trained.state_dict()}, tmp_path / "ckpt.pth")
    (tmp_path / "names.txt").write_text("\n".join(CLASSES) + "\n")
    out = tmp_path / "models" / "user.pt"
    rc = main(["export-model", f"{src}:build", "--weights", str(tmp_path / "ckpt.pth"), "--input-size", "45x80",
               "--classes", str(tmp_path / "names.txt"), "--imagenet", "--sigma", "0.5", "--out", str(out), "--json"])
    printed = json.loads(capsys.readouterr().out)
    assert rc == 0 and printed["num_classes"] == 3 and printed["input_size"] == [45, 80] and printed["sigma"] == 0.5
    model = load_model(out)
    x = torch.rand(3, 3, *SIZE)
    torch.testing.assert_close(model(x), normalised_reference(trained, x), rtol=1e-5, atol=1e-5)
    # a TorchScript file as SOURCE: metadata added, output unchanged; a list of class names
    plain = tmp_path / "plain.pt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)   # torch.jit is deprecated in torch 2.x, and still works
        torch.jit.script(trained).save(str(plain))
    rc = main(["export-model", str(plain), "--input-size", "45x80", "--classes", "x,y,z", "--out", str(tmp_path / "again.pt")])
    assert rc == 0 and "3 classes" in capsys.readouterr().out
    again = load_model(tmp_path / "again.pt")
    assert again.class_names == ["x", "y", "z"]
    with torch.no_grad():
        torch.testing.assert_close(again(x), trained(x))


@pytest.mark.parametrize("argv, needle", [
    (["nowhere.py:build"], "not found"),
    (["{src}:missing"], "has no 'missing'"),
    (["{src}:build", "--weights", "{bad}"], "does not fit the module"),
    (["{src}:build", "--classes", "a,b"], "class names"),
    (["{src}:build", "--imagenet", "--mean", "0.5"], "exclude each other"),
])
def test_cli_export_model_bad_input_is_one_line(tmp_path, capsys, argv, needle):
    src = tmp_path / "user_net.py"
    src.write_text(textwrap.dedent(USER_FILE))
    torch.save(torch.nn.Linear(2, 2).state_dict(), tmp_path / "bad.pth")
    argv = [a.format(src=src, bad=tmp_path / "bad.pth") for a in argv]
    if "--classes" not in argv:
        argv += ["--classes", "a,b,c"]
    rc = main(["export-model", *argv, "--input-size", "45x80", "--out", str(tmp_path / "o.pt")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and needle in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o.pt").exists()


def test_shipped_classes_stay_untouched():
    """The demo model keeps loading (the export path adds, it does not change the contract)."""
    model = load_model(REPO / "bags" / "models" / "classifier_sigma0.50.pt")
    assert model.num_classes == 12 and np.isclose(model.meta["sigma"], 0.5)
