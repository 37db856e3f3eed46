"""`pws bench`: a smoke run fills every table and writes the JSON, report and plots; the pieces the
bench adds on top of the core (paper rule read off a pairwise run, capped grids, peak memory) are
checked against the core itself. No timing is asserted anywhere."""
from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from pws_ros.bench import SMOKE, PeakMemory, capped_plan, grid_plan, paper_rule, scene_ids
from pws_ros.bench.tables import accuracy, certified_at
from pws_ros.cli import main
from pws_ros.core.bounds import render_plan
from pws_ros.core.certify import CertifyConfig, certify, certify_rendered
from pws_ros.core.cloud import Cloud
from pws_ros.core.errors import PwsError
from pws_ros.core.model import load_model, save_model
from pws_ros.core.partition import plan_partitions, validate_grid

H, W = 18, 32
CLASSES = ["crate", "barrel", "beach_ball", "traffic_cone", "ring", "chair", "table", "lamp", "snowman", "mushroom",
           "dumbbell", "block_tower"]


class BiasedNet(torch.nn.Module):
    """Class 0 ("crate", the class of bench scene 0) unless the red mean is far from 0.4; TorchScript-able."""

    def __init__(self, num_classes: int = 12):
        super().__init__()
        self.register_buffer("bias", torch.linspace(1.0, 0.0, num_classes))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        m = x[:, 0].mean(dim=(1, 2))
        return self.bias.unsqueeze(0) * (1.0 - 4.0 * (m - 0.4).abs()).unsqueeze(1) * 8.0


class Identity(torch.nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * 1.0


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory):
    from pws_ros.sim.train import save_denoiser

    d = tmp_path_factory.mktemp("models")
    for key in ("0.25", "0.50"):
        save_model(BiasedNet(), d / f"classifier_sigma{key}.pt", CLASSES, input_size=(H, W), meta={"sigma": float(key)})
    save_denoiser(Identity(), d / "denoiser_sigma0.50.pt", 0.5, (H, W))
    return d


@pytest.fixture(scope="module")
def smoke_run(models_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_out")
    rc = main(["bench", "--preset", "smoke", "--models", str(models_dir), "--out", str(out), "--seed", "3"])
    assert rc == 0
    return out, json.loads((out / "bench.json").read_text())


def test_smoke_run_writes_every_file(smoke_run):
    out, res = smoke_run
    for name in ("report.md", "bench.json", "frames.png", "radius_curves.png", "sigma.png", "partitions.png",
                 "time_breakdown.png", "scaling.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert (out / "frames.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(res["plots"]) == sorted(p.name for p in out.glob("*.png"))


def test_json_records_machine_seeds_and_versions(smoke_run):
    _, res = smoke_run
    m = res["machine"]
    for key in ("python", "torch", "numpy", "torch_threads", "cpu_count", "device", "platform"):
        assert m[key] not in (None, ""), key
    assert res["settings"]["seed"] == 3 and res["settings"]["preset"] == "smoke"
    assert res["image_size"] == [W, H]
    assert set(res["models"]) == {"0.25", "0.50", "0.75", "denoiser"}
    assert res["models"]["0.75"] is None and len(res["models"]["0.50"]["sha256_16"]) == 16
    assert res["total_seconds"] > 0 and set(res["stage_seconds"]) == {
        "throughput", "plans", "certificates", "shipped", "sigma", "partitions", "empirical", "denoiser", "scaling"}


def test_every_table_is_filled(smoke_run):
    _, res = smoke_run
    s, summ = res["settings"], res["summary"]
    ncert = s["cert_scenes"]
    # the shipped defaults: a 640x480 camera with surfel imaging on every certified scene and axis, next to CMS
    assert len(res["shipped"]) == ncert * len(s["cert_axes"])
    for r in res["shipped"]:
        assert r["camera"] == [640, 480] and r.get("imaging") == "surfel" and r["anchors"] >= 1, r
        assert r["classifier_calls"] <= 64 + 24 * 256   # the shipped budget: n0 + num_anchors * n
        # the packing bound is a lower bound on the anchors of any set with these radii, so on these too
        assert 1 <= r["packing_anchor_bound"] <= r["anchors"], r
    assert [r["axis"] for r in summ["shipped"]] == s["cert_axes"]
    # frames: every planned axis has N for every method
    assert [r["axis"] for r in summ["frames"]] == s["plan_axes"]
    for row in summ["frames"]:
        for m in ("pws", "pws_l", "pws_of"):
            assert row[m]["scenes"] >= 1 and row[m]["median"] >= 3, (row["axis"], m)
    # one-frame methods on every planned scene, PwS (dense) on the certified ones
    recs = res["plans"]["records"]
    assert {(r["scene"], r["method"]) for r in recs} >= {(sc, m) for sc, _ in scene_ids(s["plan_scenes"]) for m in ("pws_l", "pws_of")}
    assert all(r["cloud"] == ("dense" if r["method"] == "pws" else "one_frame") for r in recs)
    assert res["plans"]["run_lengths"] and res["plans"]["run_lengths"][0]["num_runs"] > 0
    # certified accuracy: every method x coverage and CMS on every certified axis
    rows = summ["certified_accuracy"]
    assert len(rows) == 10
    for r in rows:
        for axis in s["cert_axes"]:
            assert r[axis][1] == ncert
    # cost rows: all methods, coverages and CMS per axis, with every stage timed
    keys = {(c["axis"], c["method"], c["coverage"]) for c in summ["costs"]}
    for axis in s["cert_axes"]:
        assert (axis, "cms", "cms") in keys
        for m in ("pws", "pws_l", "pws_of"):
            for cov in ("paper", "pairwise", "anchors"):
                assert (axis, m, cov) in keys
    for c in summ["costs"]:
        assert set(c["timings"]) == {"plan", "render", "inference", "statistics", "total"}
        assert c["classifier_calls"] > 0 and c["calls_ratio_to_cms"] > 0 and c["overhead_ratio"] > 0
    # curves, sigma, partitions, empirical, denoiser, scaling
    for axis in s["cert_axes"]:
        c = summ["curves"][axis]
        assert len(c["radii"]) == 9 and len(c["cms"]) == 9 and len(c["pws_of/pairwise"]) == 9
    assert [r["sigma"] for r in summ["sigma"]] == s["sigmas"]
    assert all(r[axis]["pairwise"][1] == ncert for r in summ["sigma"] for axis in s["cert_axes"])
    assert [p["num_partitions"] for p in summ["partitions"]] == s["partition_counts"]
    assert all(p["pairwise"][1] == ncert for p in summ["partitions"])
    assert [e["axis"] for e in summ["empirical"]] == s["cert_axes"] and all(e["n"] == ncert for e in summ["empirical"])
    assert {(r["classifier"], r["denoiser"]) for r in summ["denoiser"]} == {("0.50", False), ("0.50", True)}
    assert all(r[axis]["pairwise"][1] == ncert for r in summ["denoiser"] for axis in s["denoiser_axes"])
    sc = res["scaling"]
    assert [r["num_partitions"] for r in sc["vs_partitions"]] == s["scaling_partitions"]
    assert all("timings" in r for r in sc["vs_image_size"]) and len(sc["vs_image_size"]) >= 1
    assert [r["fraction"] for r in sc["vs_cloud_size"]] == s["scaling_cloud_fractions"]
    assert all(r["planned_partitions"] >= 3 for r in sc["vs_cloud_size"])
    # claims: the paper's six and the shipped defaults' (g), with a verdict and evidence
    assert [c["id"] for c in res["claims"]] == list("abcdefg")
    for c in res["claims"]:
        assert c["verdict"] in ("holds", "partly holds", "fails", "inconclusive", "holds (not strictly)") and c["evidence"]
    assert res["full_run_estimate"]["total_seconds"] > 0


def test_records_are_consistent(smoke_run):
    _, res = smoke_run
    s = res["settings"]
    for r in res["certificates"]:
        assert "error" not in r, r.get("error")
        if r["method"] == "cms":
            assert r["classifier_calls"] == s["cms_n0"] + s["cms_n"]
            continue
        N = r["num_partitions"]
        assert 3 <= N <= s["cert_max_partitions"] and N % 2 == 1
        assert (r["capped_from"] is None) == (r["planned_partitions"] <= s["cert_max_partitions"])
        assert (r["refined_from"] is None) == (r["planned_partitions"] >= s["cert_min_partitions"])
        assert N == min(max(r["planned_partitions"], s["cert_min_partitions"]), s["cert_max_partitions"])
        if r["coverage"] == "anchors":
            assert r["classifier_calls"] == s["n0"] + r["num_bounds"] * s["anchor_n"]
        else:
            assert r["classifier_calls"] == s["n0"] + N * s["n"] and r["num_bounds"] == N
        t = r["timings"]
        assert t["total"] >= t["plan"] + t["render"] - 1e-9
        assert 0 <= r["radius"] <= r["radius_requested"] * (1 + 1e-12)
        assert r["certified"] == (r["status"] == "certified")
    # the biased classifier says "crate" everywhere: the certified accuracy is the crate scenes' share
    crate = [r for r in res["certificates"] if r["coverage"] == "pairwise" and r["class_name"] == "crate"]
    assert crate and all(r["label"] == 0 for r in crate)
    # certified implies empirically robust implies benign on the same scene (up to noise, here deterministic)
    for e in res["empirical"]:
        assert e["num_perturbations"] == s["empirical_perturbations"]
        assert e["classifier_calls"] == (s["empirical_perturbations"] + 1) * s["empirical_n"] + 1


def test_report_has_every_section_and_no_nan(smoke_run):
    out, _ = smoke_run
    text = (out / "report.md").read_text()
    for head in ("## Settings", "## The paper's claims on our world", "## Frames needed per certificate", "## Certified accuracy",
                 "## Cost per certificate", "### Noise level", "### Number of partitions", "### Certified vs empirical",
                 "### Denoiser", "## Scaling", "## Run"):
        assert head in text, head
    assert "nan" not in text.lower().replace("nanoseconds", "")
    for c in "abcdefg":
        assert f"| ({c}) |" in text
    assert "## The shipped defaults" in text


def test_bench_needs_the_models(tmp_path, capsys):
    rc = main(["bench", "--preset", "smoke", "--models", str(tmp_path / "none"), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "models folder not found" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    rc = main(["bench", "--preset", "smoke", "--models", str(tmp_path / "empty"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "classifier_sigma0.50.pt" in capsys.readouterr().err


def test_settings_validate():
    from pws_ros.bench import FULL, QUICK

    for preset in (SMOKE, QUICK, FULL):
        preset.validate()
    with pytest.raises(PwsError):
        replace(SMOKE, cert_max_partitions=4).validate()
    with pytest.raises(PwsError):
        replace(SMOKE, sigmas=(0.25,)).validate()
    with pytest.raises(PwsError):
        replace(SMOKE, cert_axes=("tz", "rx")).validate()  # rx is not planned in the smoke preset
    assert scene_ids(3) == [(0, 0), (1, 7), (2, 14)]


# ---- the bench's own pieces against the core ------------------------------------------------

def _scene(seed=0, n=8000):
    """A tilted, smoothly coloured plane densely sampled (no holes at 32x24)."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.9, 0.9, n), rng.uniform(-0.7, 0.7, n)
    pts = np.stack([x, y, 1.5 + 0.2 * x], axis=1)
    cols = np.stack([0.4 + 0.1 * np.sin(3 * x), 0.5 + 0.2 * np.cos(2 * y), 0.3 + 0.1 * x], axis=1).astype(np.float32)
    return Cloud(pts, cols)


# (sigma, n, seed, radius): certified, not certified (radius 0 and partial), abstain
@pytest.mark.parametrize("sigma,n,seed,radius", [(0.5, 64, 0, 0.01), (0.12, 64, 5, 0.05), (0.5, 4, 3, 0.01), (1.0, 32, 7, 0.06),
                                                 (1.0, 64, 4, 0.05)])
def test_paper_rule_matches_core_paper_coverage(small_camera, tmp_path, sigma, n, seed, radius):
    path = save_model(BiasedNet(), tmp_path / "m.pt", CLASSES, input_size=(small_camera.height, small_camera.width))
    model = load_model(path)
    cloud = _scene(seed)
    plan = grid_plan("pws_of", "tz", radius, 9)
    rendered = render_plan(cloud, small_camera, plan)
    cfg = CertifyConfig(imaging="paper", sigma=sigma, n0=16, n=n, seed=seed, coverage="pairwise")
    pw = certify_rendered(rendered, model, cfg)
    paper = certify_rendered(rendered, model, replace(cfg, coverage="paper"))
    assert pw.p_a_lower == paper.p_a_lower  # same seed, same counts
    decided = paper_rule(pw.p_a_lower, rendered.pair_bound_sq, plan.alphas, sigma)
    assert decided == (paper.status, paper.certified, paper.radius)
    # and certify() on the same plan (streamed frames) decides the same
    streamed = certify(cloud, small_camera, model, "tz", radius, "pws_of", replace(cfg, coverage="paper"), plan=plan)
    assert (streamed.status, streamed.certified, streamed.radius) == decided


def test_paper_rule_brute_force():
    rng = np.random.default_rng(5)
    for _ in range(200):
        N = int(rng.choice([3, 5, 7, 9]))
        alphas = np.linspace(-1, 1, N)
        alphas[N // 2] = 0.0
        p = rng.uniform(0.4, 1.0, N)
        B = rng.uniform(0, 0.3, N - 1)
        status, certified, radius = paper_rule(p, B, alphas, 0.5)
        from scipy.stats import norm

        R = np.where(p > 0.5, 0.5 * norm.ppf(np.minimum(p, 1 - 1e-16)), 0.0)
        c = N // 2
        best = 0
        for j in range(1, c + 1):  # every symmetric sub-interval is checked independently
            if np.sqrt(B[c - j : c + j] / 2).max() < R[c - j : c + j + 1].min():
                best = j
            else:
                break
        if R[c] <= 0:
            assert status == "abstain" and radius == 0.0
        else:
            assert radius == alphas[c + best] and certified == (best == c)


def test_capped_plan(small_camera):
    cloud = _scene(1, 3000)
    plan = plan_partitions(cloud, small_camera, "tz", 0.05, "pws")
    N = plan.num_partitions
    assert N > 5
    assert capped_plan(plan, N) is plan and capped_plan(plan, N + 2, N) is plan
    capped = capped_plan(plan, 5)
    assert capped.num_partitions == 5 and len(capped.alphas) == 5
    validate_grid(capped.alphas, 0.05)
    assert capped.details["capped_from"] == N and capped.details["lemma1_holds"] is None
    refined = capped_plan(plan, N + 40, N + 20)
    assert N % 2 == 1 and refined.num_partitions == N + 20
    validate_grid(refined.alphas, 0.05)
    assert refined.details["refined_from"] == N and refined.details["lemma1_holds"] == plan.details["lemma1_holds"]
    g = grid_plan("pws_of", "ry", 0.01, 7)
    assert g.num_partitions == 7 and g.alphas[3] == 0.0 and math.isclose(g.alphas[-1], 0.01)


def test_accuracy_helpers():
    recs = [{"method": "pws_of", "status": "not_certified", "correct": True, "radius": 0.5, "radius_requested": 1.0},
            {"method": "pws_of", "status": "certified", "correct": True, "radius": 1.0, "radius_requested": 1.0},
            {"method": "pws_of", "status": "certified", "correct": False, "radius": 1.0, "radius_requested": 1.0},
            {"method": "cms", "status": "certified", "correct": True, "radius": 2.0, "radius_requested": 1.0},
            {"method": "cms", "status": "abstain", "correct": False, "radius": 0.0, "radius_requested": 1.0}]
    assert accuracy(recs) == (2, 5)
    assert accuracy(recs, 0.5) == (3, 5)
    assert accuracy(recs, 0.0) == (3, 5)
    assert certified_at(recs[3], 1.99) and not certified_at(recs[3], 2.0)


def test_peak_memory_sees_an_allocation():
    import mmap
    import time

    with PeakMemory(torch.device("cpu"), interval=0.001) as mem:
        # fresh anonymous pages (an ndarray could reuse memory the allocator kept from earlier tests)
        buf = mmap.mmap(-1, 40 * 2**20)
        a = np.frombuffer(buf, dtype=np.uint8)
        a[::4096] = 1  # touch every page
        time.sleep(0.05)
        del a
        buf.close()
    assert mem.peak_bytes is not None, "no resident-set size (/proc/self/statm) on this Linux machine"
    assert mem.peak_bytes >= 30 * 2**20


def test_gpu_bench_compares_certificates_across_devices_and_times_a_frame(tmp_path):
    """pws_ros.bench.gpu: the cpu/cuda comparison names every certificate that differs (status or radius),
    counts the rest as identical, and a CPU run of the geometry case on the demo gives one timed row per
    axis whose stages add up to no more than its total (no CUDA needed)."""
    from pws_ros.bench import gpu
    from pws_ros.bridge.config import PwsConfig
    from pws_ros.replay import ReplayOptions

    def row(frame, axis, device, share, status="certified"):
        return {"case": "c", "device": device, "frame": frame, "axis": axis, "share": share, "status": status}

    rows = [row(0, "tz", "cpu", 1.0), row(0, "tz", "cuda", 1.0), row(0, "ry", "cpu", 0.5), row(0, "ry", "cuda", 0.25),
            row(1, "tz", "cpu", 0.0, "abstain"), row(1, "tz", "cuda", 0.0, "not_certified"), row(1, "ry", "cpu", 1.0)]
    lines = gpu._compare(rows, "c")
    assert lines[0] == "c: 1 certificates identical on cpu and cuda, 2 differ"
    assert lines[1:] == ["  frame 0 ry: cpu 0.5 cuda 0.25", "  frame 1 tz: cpu 0.0 cuda 0.0"]
    demo = Path(__file__).resolve().parents[1] / "bags" / "demo"
    got = gpu._run("geometry demo", "cpu", ReplayOptions(bag=demo, config=PwsConfig(axes=("tz", "ry"))), size=(60, 80), frames=1)
    assert [r["axis"] for r in got] == ["tz", "ry"] and all(r["device"] == "cpu" and r["frame"] == 0 for r in got)
    for r in got:
        assert sum(r[k] for k in ("plan", "render", "bounds", "inference", "statistics")) <= r["total"] + 1e-3
        assert 0.0 <= r["share"] <= 1.0 and r["calls"] > 0
