"""What ``pws bench`` measures and how much of it: the ``quick``, ``full`` and ``smoke`` presets.

Every number of a preset is written into the report and the JSON, so a reader knows which
settings produced the figures. The scenes are held-out scenes of :mod:`pws_ros.sim` (seeds ``0 ..``,
disjoint from the training seeds): scene ``i`` is seed ``i`` (class ``i % 12``) seen from canonical
view ``(7 i) % 24``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

from ..core.errors import require
from ..core.motion import AXES, parse_axis

PAPER_CMS_SAMPLES = 10_000  # the CMS sample count the paper's Table 1 compares with


@dataclass(frozen=True)
class BenchSettings:
    preset: str
    # Table 1 analogue (planning only)
    plan_scenes: int                 # scenes planned with PwS-L and PwS-OF (one-frame cloud), every plan axis
    plan_axes: tuple[str, ...]
    pws_plan_scenes: int             # scenes planned with PwS on the dense cloud for the axes that are not certified
    run_length_axes: tuple[str, ...]  # axes whose dense-cloud run-length quantiles are reported
    run_length_scenes: int           # on the first this many certified scenes
    # certification (Tables 2-3 analogue)
    cert_scenes: int                 # scenes certified (PwS on these is planned on the dense cloud for cert_axes)
    cert_axes: tuple[str, ...]
    n0: int
    n: int                           # noise samples per partition frame (paper / pairwise coverage)
    anchor_n: int                    # noise samples per anchor frame (anchors coverage)
    num_anchors: int
    cert_max_partitions: int         # grids with more partitions are certified on this many (odd) instead
    cert_min_partitions: int         # grids with fewer partitions are refined to this many (resolves the radius curve)
    cms_n0: int
    cms_n: int
    # ablations
    sigmas: tuple[float, ...]
    partition_counts: tuple[int, ...]
    partition_axis: str
    empirical_perturbations: int
    empirical_n: int                 # noise samples per perturbed frame (majority vote)
    denoiser_axes: tuple[str, ...]
    denoiser_classifiers: tuple[str, ...]  # "0.50", "0.25": classifier files used behind the sigma-0.5 denoiser
    denoiser_n: int                  # noise samples per partition frame in the denoiser ablation (with and without)
    # scaling
    scaling_partitions: tuple[int, ...]
    scaling_sizes: tuple[tuple[int, int], ...]  # (width, height); () = the model's size only
    scaling_cloud_fractions: tuple[float, ...]
    scaling_n: int
    scaling_axis: str = "tz"
    # common
    alpha: float = 0.01
    seed: int = 0
    batch_size: int = 250
    delta_px: float | None = None    # PwS-OF delta (pixels); None = partition.DEFAULT_DELTA_PX
    background: float = 0.0
    samples_per_pixel: float = 6.0   # dense-cloud density (sim default)
    expected_minutes: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)

    def validate(self) -> "BenchSettings":
        for name in ("plan_scenes", "cert_scenes", "n0", "n", "anchor_n", "num_anchors", "cms_n0", "cms_n",
                     "empirical_perturbations", "empirical_n", "scaling_n", "batch_size", "denoiser_n"):
            require(int(getattr(self, name)) >= 1, f"bench setting {name} must be >= 1, got {getattr(self, name)}")
        require(self.run_length_scenes >= 0, f"bench setting run_length_scenes must be >= 0, got {self.run_length_scenes}")
        require(self.pws_plan_scenes >= 0, f"bench setting pws_plan_scenes must be >= 0, got {self.pws_plan_scenes}")
        require(self.plan_scenes >= self.cert_scenes, "bench: plan_scenes must be >= cert_scenes")
        require(self.cert_max_partitions >= 3 and self.cert_max_partitions % 2 == 1,
                f"bench setting cert_max_partitions must be odd and >= 3, got {self.cert_max_partitions}")
        require(3 <= self.cert_min_partitions <= self.cert_max_partitions and self.cert_min_partitions % 2 == 1,
                f"bench setting cert_min_partitions must be odd, >= 3 and <= cert_max_partitions, got {self.cert_min_partitions}")
        for ax in self.plan_axes + self.cert_axes + self.denoiser_axes + self.run_length_axes + (self.partition_axis, self.scaling_axis):
            parse_axis(ax)
        require(set(self.cert_axes) <= set(self.plan_axes), "bench: every certified axis must be planned")
        require(set(self.denoiser_axes) <= set(self.cert_axes), "bench: denoiser axes must be certified axes")
        require(set(self.run_length_axes) <= set(self.cert_axes), "bench: run-length axes must be certified axes")
        require(self.partition_axis in self.cert_axes, "bench: the partition-ablation axis must be a certified axis")
        require(all(s > 0 for s in self.sigmas) and 0.5 in self.sigmas, "bench: sigmas must be positive and include 0.5")
        require(all(int(c) >= 3 and int(c) % 2 == 1 for c in self.partition_counts), "bench: partition counts must be odd and >= 3")
        require(all(int(c) >= 3 and int(c) % 2 == 1 for c in self.scaling_partitions), "bench: scaling partition counts must be odd and >= 3")
        require(all(0 < f <= 1 for f in self.scaling_cloud_fractions), "bench: cloud fractions must lie in (0, 1]")
        require(all(c in ("0.50", "0.25") for c in self.denoiser_classifiers), "bench: denoiser classifiers must be '0.50' or '0.25'")
        require(0 < self.alpha < 1, f"bench: alpha must lie in (0, 1), got {self.alpha}")
        return self

    def with_seed(self, seed: int) -> "BenchSettings":
        return replace(self, seed=int(seed))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["plan_axes"] = list(self.plan_axes)
        return d


def scene_ids(count: int) -> list[tuple[int, int]]:
    """``(scene_seed, view_index)`` of the first ``count`` bench scenes."""
    return [(i, (7 * i) % 24) for i in range(int(count))]


QUICK = BenchSettings(
    preset="quick",
    plan_scenes=6, plan_axes=AXES, pws_plan_scenes=1, run_length_axes=("tz",), run_length_scenes=1,
    cert_scenes=3, cert_axes=("tz", "ry"),
    n0=64, n=64, anchor_n=128, num_anchors=9, cert_max_partitions=33, cert_min_partitions=9,
    cms_n0=32, cms_n=256,
    sigmas=(0.25, 0.5, 0.75), partition_counts=(3, 9, 33, 129), partition_axis="tz",
    empirical_perturbations=100, empirical_n=16, denoiser_axes=("tz",), denoiser_classifiers=("0.50",), denoiser_n=32,
    scaling_partitions=(3, 9, 33, 129, 513), scaling_sizes=((80, 45), (160, 90), (320, 180)),
    scaling_cloud_fractions=(0.1, 0.3, 1.0), scaling_n=2,
    expected_minutes="about 4-6 min on 2 idle CPU cores with 1 torch thread (longer when the cores are shared)",
    notes=("quick: 6 planned scenes, 3 certified scenes (one per class), n = 64 noise samples per partition frame (paper: "
           "10 000), certification grids capped at 33 partitions, CMS n = 256 (paper: 10 000), 16 noise samples per empirical "
           "perturbation, 32 per frame in the denoiser ablation; PwS on the dense cloud planned on the certified scenes for "
           "tz/ry and on 1 scene for the other axes",),
)

FULL = BenchSettings(
    preset="full",
    plan_scenes=48, plan_axes=AXES, pws_plan_scenes=6, run_length_axes=("tz", "ry"), run_length_scenes=6,
    cert_scenes=24, cert_axes=("tz", "ry"),
    n0=100, n=1000, anchor_n=1000, num_anchors=9, cert_max_partitions=129, cert_min_partitions=17,
    cms_n0=100, cms_n=1000,
    sigmas=(0.25, 0.5, 0.75), partition_counts=(3, 17, 65, 129, 257), partition_axis="tz",
    empirical_perturbations=100, empirical_n=100, denoiser_axes=("tz", "ry"), denoiser_classifiers=("0.50", "0.25"),
    denoiser_n=200,
    scaling_partitions=(3, 33, 129, 513, 2049), scaling_sizes=((80, 45), (160, 90), (320, 180), (640, 360)),
    scaling_cloud_fractions=(0.03, 0.1, 0.3, 1.0), scaling_n=8,
    expected_minutes="about 6 h on 2 idle CPU cores with 1 torch thread (≈ 23 M classifier calls and about half an hour "
                     "of planning on dense clouds; the quick report extrapolates it from its own measurements); about 1 h "
                     "with --device cuda (planning stays on the CPU)",
    notes=("full: 48 planned scenes, 24 certified scenes (2 per class), n = 1000 noise samples per partition frame (paper: "
           "10 000), certification grids capped at 129 partitions, CMS n0 = 100, n = 1000 (the CMS code's setting), 100 noise "
           "samples per empirical perturbation",),
)

SMOKE = BenchSettings(
    preset="smoke",
    plan_scenes=2, plan_axes=("tz", "ry"), pws_plan_scenes=1, run_length_axes=("tz",), run_length_scenes=1,
    cert_scenes=1, cert_axes=("tz", "ry"),
    n0=8, n=16, anchor_n=16, num_anchors=3, cert_max_partitions=5, cert_min_partitions=5,
    cms_n0=4, cms_n=16,
    sigmas=(0.25, 0.5), partition_counts=(3, 5), partition_axis="tz",
    empirical_perturbations=4, empirical_n=2, denoiser_axes=("tz",), denoiser_classifiers=("0.50",), denoiser_n=16,
    scaling_partitions=(3, 5), scaling_sizes=(), scaling_cloud_fractions=(0.5, 1.0), scaling_n=1,
    batch_size=64, samples_per_pixel=2.0,
    expected_minutes="seconds (tests only)",
    notes=("smoke: a test-sized run; its numbers mean nothing",),
)

PRESETS = {"quick": QUICK, "full": FULL, "smoke": SMOKE}
