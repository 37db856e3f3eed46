from __future__ import annotations

import json
import zipfile

import pytest
import torch

from pws_ros.core.errors import PwsError
from pws_ros.core.model import LoadedModel, load_denoiser, load_model, save_model, sidecar_path


def _quiet_script(module):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.script(module)


class WrongShapeNet(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(2,))  # (B, 3, W): not (B, C)


class NaNNet(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.mean(dim=(2, 3)) * float("nan")


class ShrinkDenoiser(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :, 1:, :]


class HalfDenoiser(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 0.5 * x


def test_round_trip_with_sidecar_and_meta(tmp_path, tiny_nets):
    net = tiny_nets.LinearNet(num_classes=3, seed=1)
    path = save_model(net, tmp_path / "net.pt", ["cat", "dog", "mug"], input_size=(24, 32), meta={"sigma": 0.5, "note": "x"})
    assert path.is_file()
    assert sidecar_path(path) == tmp_path / "net.classes.txt"
    assert sidecar_path(path).read_text().splitlines() == ["cat", "dog", "mug"]
    with zipfile.ZipFile(path) as zf:
        name = next(n for n in zf.namelist() if n.endswith("extra/pws.json"))
        info = json.loads(zf.read(name))
    assert info["class_names"] == ["cat", "dog", "mug"] and info["input_height"] == 24 and info["input_width"] == 32

    m = load_model(path)
    assert isinstance(m, LoadedModel)
    assert m.class_names == ["cat", "dog", "mug"] and m.num_classes == 3
    assert m.input_size == (24, 32)
    assert m.meta["sigma"] == 0.5 and m.meta["note"] == "x"
    assert m.device == torch.device("cpu") and m.path == str(path)
    x = torch.rand(5, 3, 24, 32, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        expected = net(x)
    assert torch.allclose(m(x), expected, atol=1e-6)


def test_class_sources_and_priority(tmp_path, tiny_nets):
    path = save_model(tiny_nets.LinearNet(3), tmp_path / "a.pt", ["x", "y", "z"], input_size=(8, 8))
    # sidecar wins over pws.json
    sidecar_path(path).write_text("p\nq\nr\n\n")
    assert load_model(path).class_names == ["p", "q", "r"]
    # no sidecar: classes.txt in the folder
    sidecar_path(path).unlink()
    (tmp_path / "classes.txt").write_text("u\nv\nw\n")
    assert load_model(path).class_names == ["u", "v", "w"]
    # neither: pws.json
    (tmp_path / "classes.txt").unlink()
    assert load_model(path).class_names == ["x", "y", "z"]
    # explicit path, explicit list
    (tmp_path / "mine.txt").write_text("a\nb\nc\n")
    assert load_model(path, classes=tmp_path / "mine.txt").class_names == ["a", "b", "c"]
    assert load_model(path, classes=["k", "l", "m"]).class_names == ["k", "l", "m"]


def test_plain_torchscript_without_meta_gets_default_names(tmp_path, tiny_nets):
    path = tmp_path / "plain.pt"
    _quiet_script(tiny_nets.LinearNet(4)).save(str(path))
    m = load_model(path)
    assert m.class_names == ["class_0", "class_1", "class_2", "class_3"]
    assert m.input_size is None and m.meta == {}


def test_unknown_size_model_rejecting_dry_run_is_validated_at_first_call(tmp_path, tiny_nets):
    path = tmp_path / "fixed.pt"
    _quiet_script(tiny_nets.FixedSizeNet(8, 8, 2)).save(str(path))
    m = load_model(path)  # 32x32 rejected: dry run skipped
    assert m.num_classes == 0
    out = m(torch.zeros(2, 3, 8, 8))
    assert out.shape == (2, 2) and m.class_names == ["class_0", "class_1"]
    with pytest.raises(PwsError, match="failed on input"):
        m(torch.zeros(1, 3, 9, 9))


def test_class_count_mismatch(tmp_path, tiny_nets):
    path = save_model(tiny_nets.LinearNet(3), tmp_path / "m.pt", ["a", "b", "c"], input_size=(8, 8))
    sidecar_path(path).write_text("a\nb\n")
    with pytest.raises(PwsError, match="2 class names but model .* outputs 3 classes"):
        load_model(path)
    with pytest.raises(PwsError, match="4 class names"):
        load_model(path, classes=["a", "b", "c", "d"])


def test_bad_class_files(tmp_path, tiny_nets):
    path = save_model(tiny_nets.LinearNet(2), tmp_path / "m.pt", ["a", "b"], input_size=(8, 8))
    with pytest.raises(PwsError, match="class file not found"):
        load_model(path, classes=tmp_path / "nope.txt")
    sidecar_path(path).write_text("a\na\n")
    with pytest.raises(PwsError, match="appears twice"):
        load_model(path)
    sidecar_path(path).write_text("\n\n")
    with pytest.raises(PwsError, match="no class names"):
        load_model(path)


def test_missing_and_not_torchscript(tmp_path):
    with pytest.raises(PwsError, match="model file not found"):
        load_model(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"definitely not a zip archive")
    with pytest.raises(PwsError, match="not a TorchScript archive"):
        load_model(junk)
    pickled = tmp_path / "state.pt"
    torch.save({"weight": torch.zeros(3)}, pickled)  # a torch.save checkpoint, not TorchScript
    with pytest.raises(PwsError, match="not a TorchScript archive"):
        load_model(pickled)
    with pytest.raises(PwsError, match="not found"):
        load_denoiser(tmp_path / "missing_denoiser.pt")


def test_wrong_output_shape_rejected(tmp_path):
    path = tmp_path / "wrong.pt"
    _quiet_script(WrongShapeNet()).save(str(path))
    with pytest.raises(PwsError, match=r"returned shape \(1, 3, 32\)"):
        load_model(path)
    # save_model refuses it as well (output does not match the class names)
    with pytest.raises(PwsError, match="expected"):
        save_model(WrongShapeNet(), tmp_path / "w2.pt", ["a", "b", "c"], input_size=(8, 8))


def test_call_checks_output_and_input(tmp_path, tiny_nets):
    m = LoadedModel(module=NaNNet(), class_names=["a", "b", "c"], input_size=None, path="nan-model", meta={},
                    device=torch.device("cpu"))
    with pytest.raises(PwsError, match="NaN or infinite"):
        m(torch.zeros(1, 3, 4, 4))
    m2 = LoadedModel(module=WrongShapeNet(), class_names=["a", "b", "c"], input_size=None, path="wrong-model", meta={},
                     device=torch.device("cpu"))
    with pytest.raises(PwsError, match=r"model wrong-model returned shape \(2, 3, 4\), expected \(B, C\)"):
        m2(torch.zeros(2, 3, 5, 4))
    m3 = load_model(save_model(tiny_nets.LinearNet(2), tmp_path / "s.pt", ["a", "b"], input_size=(8, 10)))
    with pytest.raises(PwsError, match=r"expects 10x8 .* is 12x8"):
        m3(torch.zeros(1, 3, 8, 12))
    with pytest.raises(PwsError, match=r"\(B, 3, H, W\)"):
        m3(torch.zeros(3, 8, 10))
    # class count of a LoadedModel that disagrees with the output
    m4 = LoadedModel(module=tiny_nets.LinearNet(3), class_names=["a", "b"], input_size=None, path="m4", meta={},
                     device=torch.device("cpu"))
    with pytest.raises(PwsError, match="expected"):
        m4(torch.zeros(1, 3, 4, 4))


def test_trace_fallback_for_unscriptable_module(tmp_path):
    class Unscriptable(torch.nn.Module):
        def forward(self, x):  # no annotations + python-only construct
            return torch.stack([x.mean(dim=(1, 2, 3)), -x.mean(dim=(1, 2, 3))], dim=1) * float(len(__import__("math").__name__))

    with pytest.raises(Exception):
        _quiet_script(Unscriptable())  # so save_model must fall back to tracing
    path = save_model(Unscriptable(), tmp_path / "traced.pt", ["pos", "neg"], input_size=(4, 6))
    m = load_model(path)
    x = torch.rand(3, 3, 4, 6, generator=torch.Generator().manual_seed(2))
    assert torch.allclose(m(x), Unscriptable()(x), atol=1e-6)


def test_denoiser(tmp_path):
    good = tmp_path / "half.pt"
    _quiet_script(HalfDenoiser()).save(str(good))
    d = load_denoiser(good)
    x = torch.rand(2, 3, 5, 7)
    assert torch.equal(d(x), 0.5 * x)
    bad = tmp_path / "shrink.pt"
    _quiet_script(ShrinkDenoiser()).save(str(bad))
    with pytest.raises(PwsError, match="keep the shape"):
        load_denoiser(bad)


def test_make_model_file_fixture(make_model_file):
    path = make_model_file()
    m = load_model(path)
    assert m.class_names == ["c0", "c1"] and m.input_size == (24, 32)
    x = torch.full((2, 3, 24, 32), 0.2)
    x[1, 0] = 0.9
    assert m(x).argmax(1).tolist() == [0, 1]
