"""Analytic surface primitives: exact ray casting, uniform surface sampling, inside tests, textures.

Every primitive lives in its own *local* frame, placed in the world by a rotation ``R`` (world from
local) and a translation ``c``: ``p_world = R @ p_local + c``. Rays are ``o + t d`` with ``d`` of any
length (``t`` is returned in units of ``d``; with ``d = R_wc @ (x, y, 1)`` it is the camera depth).

Colours are functions of the local surface position only (:class:`Texture`), so a ray caster and a
surface sampler that hit the same surface point see the same albedo.

Kept as one module on purpose (about 530 lines): the six primitives implement one interface
(intersect, sample uniformly by area, inside test) with shared ray helpers (quadric roots, disc
caps, nearest positive hit; the cylinder and the cone share their nearest-hit search as solids of
revolution); each class is short, and splitting them would scatter one algorithm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

EPS = 1e-9


# ------------------------------------------------------------------------------------------------
# textures
# ------------------------------------------------------------------------------------------------
@dataclass
class Texture:
    """Albedo as a function of the local position ``p`` (N, 3) -> (N, 3) in [0, 1].

    kinds: ``solid`` (colors[0]); ``stripes`` (bands of ``period`` m along ``axis``); ``checker``
    (3-D cubes of side ``period``); ``segments`` (``count`` azimuthal sectors around local z);
    ``dots`` (spots of radius ``radius`` on a lattice of ``period``); ``rings`` (radial bands in xy).
    Colours cycle through ``colors``. ``grain`` adds a smooth multiplicative variation.
    """

    kind: str = "solid"
    colors: tuple = ((0.5, 0.5, 0.5),)
    period: float = 0.1
    axis: tuple = (0.0, 0.0, 1.0)
    count: int = 6
    radius: float = 0.03
    grain: float = 0.0
    offset: float = 0.0

    def __call__(self, p: np.ndarray) -> np.ndarray:
        cols = np.asarray(self.colors, dtype=np.float64).reshape(-1, 3)
        k = len(cols)
        if self.kind == "solid" or k == 1:
            idx = np.zeros(len(p), dtype=np.int64)
        elif self.kind == "stripes":
            s = p @ np.asarray(self.axis, dtype=np.float64) / self.period + self.offset
            idx = np.floor(s).astype(np.int64) % k
        elif self.kind == "checker":
            q = np.floor(p / self.period + self.offset).astype(np.int64)
            idx = (q[:, 0] + q[:, 1] + q[:, 2]) % k
        elif self.kind == "segments":
            ang = np.arctan2(p[:, 1], p[:, 0]) + math.pi
            idx = np.floor(ang / (2 * math.pi) * self.count).astype(np.int64) % k
        elif self.kind == "rings":
            r = np.hypot(p[:, 0], p[:, 1]) / self.period + self.offset
            idx = np.floor(r).astype(np.int64) % k
        elif self.kind == "dots":
            q = p / self.period
            d = np.linalg.norm((q - np.round(q)) * self.period, axis=1)
            idx = np.where(d < self.radius, 1, 0) % k
        else:  # pragma: no cover - programming error
            raise ValueError(f"unknown texture kind {self.kind}")
        out = cols[idx]
        if self.grain:
            g = 1.0 + self.grain * np.sin(p[:, 0] * 23.0 + 1.7 * np.sin(p[:, 1] * 17.0)) * np.cos(p[:, 2] * 19.0)
            out = out * g[:, None]
        return np.clip(out, 0.0, 1.0)


# ------------------------------------------------------------------------------------------------
# primitives
# ------------------------------------------------------------------------------------------------
def _no_hit(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.full(n, np.inf), np.zeros((n, 3))


def _smallest_positive(*ts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise smallest t > EPS among candidates (inf if none) and which candidate won."""
    stack = np.stack([np.where(np.isfinite(t) & (t > EPS), t, np.inf) for t in ts], axis=0)
    which = np.argmin(stack, axis=0)
    return np.take_along_axis(stack, which[None], axis=0)[0], which


def _quadratic_roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Real roots (t0 <= t1) of ``a t^2 + 2 b t + c``; NaN where none (numerically stable form)."""
    disc = b * b - a * c
    ok = (disc >= 0) & (np.abs(a) > 1e-15)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    q = -(b + np.copysign(sq, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        r0 = np.where(ok, q / np.where(ok, a, 1.0), np.nan)
        r1 = np.where(ok & (np.abs(q) > 0), c / np.where(q == 0, 1.0, q), np.nan)
    t0 = np.fmin(r0, r1)
    t1 = np.fmax(r0, r1)
    return t0, t1


def _along(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The points ``o + t d`` (``o`` where ``t`` is not finite: callers mask those rays)."""
    return o + np.where(np.isfinite(t), t, 0.0)[:, None] * d


def _cylindrical(rho, th: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Points ``(rho cos th, rho sin th, z)`` (N, 3) around the local z axis."""
    return np.stack([rho * np.cos(th), rho * np.sin(th), z], axis=1)


def _side_hits(o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, z_lo: float,
               z_hi: float) -> list[np.ndarray]:
    """Both roots of a quadric side ``a t^2 + 2 b t + c = 0``, kept where the hit's local z lies in
    ``[z_lo, z_hi]`` (inf elsewhere)."""
    hits = []
    for s in _quadratic_roots(a, b, c):
        z = _along(o, d, s)[:, 2]
        hits.append(np.where(np.isfinite(s) & (z >= z_lo) & (z <= z_hi), s, np.inf))
    return hits


def _disc_hit(o: np.ndarray, d: np.ndarray, z0: float, r: float) -> np.ndarray:
    """``t`` where rays meet the disc of radius ``r`` around the local z axis at height ``z0`` (inf: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z0 - o[:, 2]) / d[:, 2]
    p = _along(o, d, t)
    x, y = p[:, 0], p[:, 1]
    return np.where(np.isfinite(t) & (x * x + y * y <= r * r), t, np.inf)


@dataclass
class Primitive:
    """Base class: subclasses implement the ``_local`` methods."""

    texture: Texture = field(default_factory=Texture)
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    c: np.ndarray = field(default_factory=lambda: np.zeros(3))

    # -- placement -------------------------------------------------------------------------------
    def placed(self, R: np.ndarray, c: np.ndarray) -> "Primitive":
        """This primitive moved by a further rigid motion ``p -> R p + c``."""
        import copy

        out = copy.copy(self)
        out.R = np.asarray(R, dtype=np.float64) @ self.R
        out.c = np.asarray(R, dtype=np.float64) @ self.c + np.asarray(c, dtype=np.float64)
        return out

    def to_local(self, p: np.ndarray) -> np.ndarray:
        return (p - self.c) @ self.R

    def to_world(self, p: np.ndarray) -> np.ndarray:
        return p @ self.R.T + self.c

    # -- world-frame API ---------------------------------------------------------------------------
    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """First hit ``t`` (inf if none), world normal and local hit point for rays ``o + t d``."""
        ol = (o - self.c) @ self.R
        dl = d @ self.R
        t, nl = self._intersect_local(ol, dl)
        pl = ol + np.where(np.isfinite(t), t, 0.0)[:, None] * dl
        return t, nl @ self.R.T, pl

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``n`` points uniform by area: world points, world normals, local points."""
        pl, nl = self._sample_local(int(n), rng)
        return self.to_world(pl), nl @ self.R.T, pl

    def contains(self, p: np.ndarray, tol: float = 1e-6) -> np.ndarray:
        """Strictly inside (by more than ``tol``) the solid, for world points."""
        return self._contains_local(self.to_local(p), tol)

    def albedo(self, p_local: np.ndarray) -> np.ndarray:
        return self.texture(p_local)

    # -- to implement: ``area`` (property) and the three ``_local`` methods ----------------------
    def _intersect_local(self, o, d):  # pragma: no cover - abstract
        raise NotImplementedError

    def _sample_local(self, n, rng):  # pragma: no cover - abstract
        raise NotImplementedError

    def _contains_local(self, p, tol):  # pragma: no cover - abstract
        raise NotImplementedError


@dataclass
class Sphere(Primitive):
    radius: float = 0.1

    @property
    def area(self) -> float:
        return 4 * math.pi * self.radius**2

    def _intersect_local(self, o, d):
        a = np.einsum("ij,ij->i", d, d)
        b = np.einsum("ij,ij->i", o, d)
        c = np.einsum("ij,ij->i", o, o) - self.radius**2
        t0, t1 = _quadratic_roots(a, b, c)
        t, _ = _smallest_positive(t0, t1)
        p = _along(o, d, t)
        return t, p / self.radius

    def _sample_local(self, n, rng):
        v = rng.normal(size=(n, 3))
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        return v * self.radius, v

    def _contains_local(self, p, tol):
        return np.linalg.norm(p, axis=1) < self.radius - tol


@dataclass
class Box(Primitive):
    half: tuple = (0.1, 0.1, 0.1)

    @property
    def area(self) -> float:
        a, b, c = self.half
        return 8 * (a * b + b * c + a * c)

    def _intersect_local(self, o, d):
        h = np.asarray(self.half, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1 = (-h - o) * inv
            t2 = (h - o) * inv
        tmin = np.fmin(t1, t2)
        tmax = np.fmax(t1, t2)
        # rays parallel to a slab: inside -> (-inf, inf), outside -> empty
        par = d == 0
        inside = np.abs(o) <= h
        tmin = np.where(par, np.where(inside, -np.inf, np.inf), tmin)
        tmax = np.where(par, np.where(inside, np.inf, -np.inf), tmax)
        tn = tmin.max(axis=1)
        tf = tmax.min(axis=1)
        hit = tf >= np.maximum(tn, EPS)
        t = np.where(hit, np.where(tn > EPS, tn, tf), np.inf)
        p = _along(o, d, t)
        q = np.abs(p) / h
        k = np.argmax(q, axis=1)
        n = np.zeros_like(p)
        n[np.arange(len(p)), k] = np.sign(p[np.arange(len(p)), k])
        return t, n

    def _sample_local(self, n, rng):
        a, b, c = self.half
        areas = np.array([b * c, b * c, a * c, a * c, a * b, a * b])
        face = rng.choice(6, size=n, p=areas / areas.sum())
        u = rng.uniform(-1, 1, size=(n, 3)) * np.asarray(self.half)
        axis = face // 2
        sign = np.where(face % 2 == 0, 1.0, -1.0)
        idx = np.arange(n)
        u[idx, axis] = sign * np.asarray(self.half)[axis]
        nrm = np.zeros((n, 3))
        nrm[idx, axis] = sign
        return u, nrm

    def _contains_local(self, p, tol):
        return np.all(np.abs(p) < np.asarray(self.half) - tol, axis=1)


@dataclass
class _Revolved(Primitive):
    """A solid of revolution around local z: a quadric side between two heights, closed by flat discs.
    The nearest hit is found here, once for both solids; a subclass gives
    ``_side_quadric(o, d)`` -> ``(a, b, c)``, the side at the roots of ``a t^2 + 2 b t + c`` along each ray;
    ``_side_heights()`` -> ``(z_lo, z_hi)``, where the side is; ``_discs()`` -> ``((height, radius), ...)``,
    a hit on disc k reporting ``which = 2 + k``; ``_normals(p, which)`` -> the local normals at the hits."""

    radius: float = 0.1

    def _intersect_local(self, o, d):
        a, b, c = self._side_quadric(o, d)
        z_lo, z_hi = self._side_heights()
        side = _side_hits(o, d, a, b, c, z_lo, z_hi)
        t, which = _smallest_positive(side[0], side[1], *(_disc_hit(o, d, z0, r) for z0, r in self._discs()))
        return t, self._normals(_along(o, d, t), which)


@dataclass
class Cylinder(_Revolved):
    """Capped cylinder around local z, ``z in [-half_height, half_height]``."""

    half_height: float = 0.1

    @property
    def area(self) -> float:
        return 2 * math.pi * self.radius * 2 * self.half_height + 2 * math.pi * self.radius**2

    def _side_quadric(self, o, d):
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - self.radius * self.radius
        return a, b, c

    def _side_heights(self):
        return -self.half_height, self.half_height

    def _discs(self):
        return (-self.half_height, self.radius), (self.half_height, self.radius)

    def _normals(self, p, which):
        n = np.zeros_like(p)
        n[:, 0] = p[:, 0] / self.radius
        n[:, 1] = p[:, 1] / self.radius
        capm = which >= 2
        n[capm] = 0.0
        n[capm, 2] = np.where(which[capm] == 2, -1.0, 1.0)
        return n

    def _sample_local(self, n, rng):
        r, h = self.radius, self.half_height
        a_side, a_cap = 2 * math.pi * r * 2 * h, math.pi * r * r
        part = rng.choice(3, size=n, p=np.array([a_side, a_cap, a_cap]) / (a_side + 2 * a_cap))
        th = rng.uniform(0, 2 * math.pi, size=n)
        rr = np.where(part == 0, r, r * np.sqrt(rng.uniform(0, 1, size=n)))
        z = np.where(part == 0, rng.uniform(-h, h, size=n), np.where(part == 1, -h, h))
        p = _cylindrical(rr, th, z)
        nrm = _cylindrical(1.0, th, np.zeros(n))
        nrm[part == 1] = (0.0, 0.0, -1.0)
        nrm[part == 2] = (0.0, 0.0, 1.0)
        return p, nrm

    def _contains_local(self, p, tol):
        return (np.hypot(p[:, 0], p[:, 1]) < self.radius - tol) & (np.abs(p[:, 2]) < self.half_height - tol)


@dataclass
class Cone(_Revolved):
    """Solid cone around local z: base disc of ``radius`` at z = 0, apex at z = ``height``."""

    height: float = 0.2

    @property
    def slant(self) -> float:
        return math.hypot(self.radius, self.height)

    @property
    def area(self) -> float:
        return math.pi * self.radius * self.slant + math.pi * self.radius**2

    def _side_quadric(self, o, d):
        k2 = (self.radius / self.height) ** 2
        w = self.height - o[:, 2]
        a = d[:, 0] ** 2 + d[:, 1] ** 2 - k2 * d[:, 2] ** 2
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + k2 * w * d[:, 2]
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - k2 * w * w
        return a, b, c

    def _side_heights(self):
        return 0.0, self.height

    def _discs(self):
        return ((0.0, self.radius),)

    def _normals(self, p, which):
        rr = np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-12)
        n = np.stack([p[:, 0] / rr, p[:, 1] / rr, np.full(len(p), self.radius / self.height)], axis=1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n[which == 2] = (0.0, 0.0, -1.0)
        return n

    def _sample_local(self, n, rng):
        R, H = self.radius, self.height
        a_side, a_cap = math.pi * R * self.slant, math.pi * R * R
        is_cap = rng.uniform(0, 1, size=n) < a_cap / (a_side + a_cap)
        th = rng.uniform(0, 2 * math.pi, size=n)
        s = np.sqrt(rng.uniform(0, 1, size=n))  # radius fraction, uniform by area on both parts
        rr = R * s
        z = np.where(is_cap, 0.0, H * (1 - s))
        p = _cylindrical(rr, th, z)
        nrm = _cylindrical(1.0, th, np.full(n, R / H))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm[is_cap] = (0.0, 0.0, -1.0)
        return p, nrm

    def _contains_local(self, p, tol):
        z = p[:, 2]
        r_at = self.radius * (1 - z / self.height)
        return (z > tol) & (z < self.height - tol) & (np.hypot(p[:, 0], p[:, 1]) < r_at - tol)


@dataclass
class Torus(Primitive):
    """Torus around local z: tube of radius ``minor`` around the circle of radius ``major``."""

    major: float = 0.2
    minor: float = 0.05

    @property
    def area(self) -> float:
        return 4 * math.pi**2 * self.major * self.minor

    def _f(self, p):
        s = np.einsum("ij,ij->i", p, p) + self.major**2 - self.minor**2
        return s * s - 4 * self.major**2 * (p[:, 0] ** 2 + p[:, 1] ** 2)

    def _intersect_local(self, o, d):
        n_rays = len(o)
        t_out, n_out = _no_hit(n_rays)
        Rm, rm = self.major, self.minor
        scale = np.linalg.norm(d, axis=1)
        du = d / np.maximum(scale, 1e-300)[:, None]
        # bounding sphere
        b = np.einsum("ij,ij->i", o, du)
        c = np.einsum("ij,ij->i", o, o) - (Rm + rm) ** 2
        disc = b * b - c
        cand = np.nonzero(disc > 0)[0]
        if cand.size == 0:
            return t_out, n_out
        t_enter = np.maximum(-b[cand] - np.sqrt(disc[cand]), 0.0)
        oo = o[cand] + t_enter[:, None] * du[cand]
        dd = du[cand]
        a = np.einsum("ij,ij->i", oo, dd)
        bb = np.einsum("ij,ij->i", oo, oo) + Rm * Rm - rm * rm
        c3 = 4 * a
        c2 = 4 * a * a + 2 * bb - 4 * Rm * Rm * (dd[:, 0] ** 2 + dd[:, 1] ** 2)
        c1 = 4 * a * bb - 8 * Rm * Rm * (oo[:, 0] * dd[:, 0] + oo[:, 1] * dd[:, 1])
        c0 = bb * bb - 4 * Rm * Rm * (oo[:, 0] ** 2 + oo[:, 1] ** 2)
        comp = np.zeros((cand.size, 4, 4))
        comp[:, 0, :] = -np.stack([c3, c2, c1, c0], axis=1)
        comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
        roots = np.linalg.eigvals(comp)
        real = np.abs(roots.imag) < 1e-6 * (1 + np.abs(roots.real))
        tr = np.where(real, roots.real, np.inf)
        tr = np.where(tr > -1e-9, tr, np.inf)  # shifted origin is on/outside the bounding sphere
        # polish each finite root with Newton steps on f(o + t d)
        for _ in range(3):
            for j in range(4):
                tj = tr[:, j]
                fin = np.isfinite(tj)
                if not fin.any():
                    continue
                p = oo + np.where(fin, tj, 0.0)[:, None] * dd
                f = self._f(p)
                s = np.einsum("ij,ij->i", p, p) + Rm * Rm - rm * rm
                grad = 4 * s[:, None] * p
                grad[:, :2] -= 8 * Rm * Rm * p[:, :2]
                fp = np.einsum("ij,ij->i", grad, dd)
                with np.errstate(divide="ignore", invalid="ignore"):
                    step = np.where(fin & (np.abs(fp) > 1e-12), f / fp, 0.0)
                tr[:, j] = np.where(fin, tj - np.clip(step, -1e-3, 1e-3), tj)
        tbest = np.min(np.where(tr >= 0, tr, np.inf), axis=1)
        ttot = tbest + t_enter
        hit_o = o[cand] + np.where(np.isfinite(ttot), ttot, 0.0)[:, None] * du[cand]
        t_world = ttot / scale[cand]
        # discard hits behind the true origin
        ok = np.isfinite(t_world) & (t_world > EPS)
        t_out[cand] = np.where(ok, t_world, np.inf)
        n_out[cand] = self._normal(hit_o)
        return t_out, n_out

    def _normal(self, p):
        rho = np.maximum(np.hypot(p[:, 0], p[:, 1]), 1e-12)
        q = np.stack([p[:, 0] / rho * self.major, p[:, 1] / rho * self.major, np.zeros(len(p))], axis=1)
        n = p - q
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def _sample_local(self, n, rng):
        out_p, out_n, got = [], [], 0
        while got < n:
            m = max(16, int((n - got) * 1.6))
            th = rng.uniform(0, 2 * math.pi, size=m)
            ph = rng.uniform(0, 2 * math.pi, size=m)
            w = (self.major + self.minor * np.cos(ph)) / (self.major + self.minor)
            keep = rng.uniform(0, 1, size=m) < w
            th, ph = th[keep], ph[keep]
            ring = self.major + self.minor * np.cos(ph)
            p = _cylindrical(ring, th, self.minor * np.sin(ph))
            nn = _cylindrical(np.cos(ph), th, np.sin(ph))
            out_p.append(p)
            out_n.append(nn)
            got += len(p)
        return np.concatenate(out_p)[:n], np.concatenate(out_n)[:n]

    def _contains_local(self, p, tol):
        return (np.hypot(p[:, 0], p[:, 1]) - self.major) ** 2 + p[:, 2] ** 2 < (self.minor - tol) ** 2


@dataclass
class Rect(Primitive):
    """A flat rectangle ``|x| <= half_u, |y| <= half_v`` in the local z = 0 plane (double sided;
    the shading normal is local +z). Has no inside."""

    half_u: float = 1.0
    half_v: float = 1.0

    @property
    def area(self) -> float:
        return 4 * self.half_u * self.half_v

    def _intersect_local(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -o[:, 2] / d[:, 2]
        tt = np.where(np.isfinite(t), t, 0.0)
        x = o[:, 0] + tt * d[:, 0]
        y = o[:, 1] + tt * d[:, 1]
        ok = np.isfinite(t) & (t > EPS) & (np.abs(x) <= self.half_u) & (np.abs(y) <= self.half_v)
        n = np.zeros((len(o), 3))
        n[:, 2] = 1.0
        return np.where(ok, t, np.inf), n

    def _sample_local(self, n, rng):
        p = np.stack([rng.uniform(-self.half_u, self.half_u, n), rng.uniform(-self.half_v, self.half_v, n), np.zeros(n)], axis=1)
        nrm = np.zeros((n, 3))
        nrm[:, 2] = 1.0
        return p, nrm

    def _contains_local(self, p, tol):
        return np.zeros(len(p), dtype=bool)


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
