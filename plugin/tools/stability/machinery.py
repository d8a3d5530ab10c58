"""The stability suite's registry of cases (`case`, CASES, CaseResult) and the ray-level machinery its cases share:
test meshes, random rays, our hits in every mode, Embree's, and the comparison against both Embree modes with the
exact float64 referee."""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

import layerbvh
from layerbvh import MISS, meshes
from layerbvh_mitsuba.ab import embree
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.repo import SCENES
from layerbvh_mitsuba.runtime.scene_geometry import collect_geometry

STIFF = SCENES / "stability"
RAYS = 40_000          # rays per ray-level case at scale 1
# Allowed rate of rays on which we are wrong by the exact float64 check. Measured: 0 rays in every
# case at scale 1 and 5; with the double-precision edge refinement switched off, 3 (slivers), 288
# (edges and vertices) and 2,315 (grazing) at scale 1. (Until this was written the rule also let us
# be as wrong as robust Embree, 12 / 473 / 3,231 rays there, which hid that.)
REAL_RATE = 1e-4


@dataclass
class CaseResult:
    case: str
    level: str                 # "rays" or "image"
    tried: int                 # rays (ray level) or pixels (image level)
    vs_default: int | None     # disagreements with Embree in its default mode
    vs_robust: int | None      # ... with embree_use_robust_intersections
    nonfinite: int             # NaN/Inf values among our hits or pixels
    passed: bool
    criterion: str             # the pass rule with the measured numbers
    notes: str = ""
    figures: dict = field(default_factory=dict)


@dataclass
class Case:
    name: str
    level: str
    what: str
    run: Callable[[float], CaseResult]


CASES: dict[str, Case] = {}


def case(name: str, level: str, what: str):
    def register(fn):
        CASES[name] = Case(name, level, what, fn)
        return fn
    return register


def run_case(name: str, scale: float = 1.0) -> CaseResult:
    return CASES[name].run(scale)


def _mi():
    return use_variant()


# -- ray level: shared machinery ---------------------------------------------------------------------


def _rng(name: str) -> np.random.Generator:
    return np.random.default_rng(zlib.crc32(name.encode()))


def scene_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """World-space triangles of a project XML scene (every mesh, as the integrator sees them)."""
    mi = _mi()
    v, f, _ = collect_geometry(mi.load_file(str(path), resx=8, resy=8)).world_triangles()
    return v.astype(np.float64), f


def bunny() -> tuple[np.ndarray, np.ndarray]:
    v, f = meshes.load_mesh(SCENES / "meshes" / "bunny.ply")
    return v.astype(np.float64), f


def trace_modes(v, f, o, d, tmax=None, **build):
    """Our hits in every mode on every branching (the default BVH and its per_ray hits returned)
    and how many rays any other mode or branching answers differently (bits of prim, t, u, v)."""
    v32 = np.asarray(v, np.float32)
    bvhs = {k: layerbvh.build(v32, f, **{**build, "branching": k}) for k in layerbvh.BRANCHINGS}
    bvh = bvhs[build.get("branching", layerbvh.DEFAULT_BRANCHING)]
    ref = bvh.trace(o, d, tmax, mode="per_ray", stats=False)
    hits = [b.trace(o, d, tmax, mode=m, stats=False) for b in bvhs.values() for m in layerbvh.MODES]
    differ = np.zeros(len(o), bool)
    for h in hits:
        for a, b in ((h.prim, ref.prim), (h.t, ref.t), (h.u, ref.u), (h.v, ref.v)):
            differ |= ~((a == b) | (np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f" else (a == b))
    return bvh, ref, int(differ.sum())


def nonfinite_hits(h) -> int:
    hit = h.prim != MISS
    return int((hit & ~(np.isfinite(h.t) & np.isfinite(h.u) & np.isfinite(h.v))).sum())


def embree_hits(v, f, o, d, tmax=None, with_t: bool = False) -> dict:
    """Embree's closest-hit prims (or (t, prim) with `with_t`), default and robust mode."""
    _mi()
    v32 = np.asarray(v, np.float32)
    out = {robust: embree.intersect(embree.scene_from_mesh(v32, f, robust), o, d, tmax) for robust in (False, True)}
    return out if with_t else {r: tp[1] for r, tp in out.items()}


def against_embree(name: str, v, f, o, d, tmax=None, extra: dict | None = None, notes: str = "",
                   traced: tuple | None = None, embree_ref: dict | None = None, **build) -> CaseResult:
    """The standard ray-level verdict. Where ours and Embree (default or robust) disagree, an exact
    float64 test of the triangles each side names decides who is wrong (`embree.wrong_answers`).
    Pass: the modes agree bit for bit, no NaN/Inf hit, and we are wrong on at most REAL_RATE x
    rays. `extra` adds {label: (value, must_be_zero)} figures. `traced` and `embree_ref`: what
    the case already has from `trace_modes` and `embree_hits` for these rays (not traced again)."""
    v32 = np.asarray(v, np.float32)
    o, d = np.asarray(o, np.float32), np.asarray(d, np.float32)
    _, h, mode_diff = traced if traced is not None else trace_modes(v32, f, o, d, tmax, **build)
    ref = embree_ref if embree_ref is not None else embree_hits(v32, f, o, d, tmax)
    dis = {r: embree.disagreements(v32, f, o, d, h.prim, p) for r, p in ref.items()}
    own = embree.disagreements(v32, f, o, d, ref[False], ref[True])
    rays = np.unique(np.concatenate([dis[False]["real_idx"], dis[True]["real_idx"], own["real_idx"]]))
    wrong = embree.wrong_answers(v32, f, o, d, {"ours": h.prim, "default": ref[False], "robust": ref[True]}, rays)
    n = len(o)
    allowed = int(REAL_RATE * n)
    bad = nonfinite_hits(h)
    extra = extra or {}
    hard = {k: val for k, (val, zero) in extra.items() if zero}
    passed = mode_diff == 0 and bad == 0 and wrong["ours"] <= allowed and all(val == 0 for val in hard.values())
    crit = (f"modes identical ({mode_diff} rays differ), NaN/Inf {bad}, wrong by exact check {wrong['ours']} <= "
            f"{allowed} ({REAL_RATE:g} x rays; Embree default / robust: {wrong['default']} / {wrong['robust']})")
    if hard:
        crit += "; " + ", ".join(f"{k} {val} = 0" for k, val in hard.items())
    soft = [f"{k} {val}" for k, (val, zero) in extra.items() if not zero]
    hit_rate = float(np.mean(h.prim != MISS))
    return CaseResult(name, "rays", n, dis[False]["real"], dis[True]["real"], bad, passed, crit,
                      "; ".join(x for x in [f"{100 * hit_rate:.1f}% hit",
                                            f"ties {dis[False]['ties']} / {dis[True]['ties']}", *soft, notes] if x),
                      {"mode_diff": mode_diff, "wrong": wrong, "embree_default_vs_robust": own["real"],
                       "ties_default": dis[False]["ties"], "ties_robust": dis[True]["ties"], "hit_rate": hit_rate,
                       **{k: val for k, (val, _) in extra.items()}})


def _n(scale: float, base: int = RAYS) -> int:
    return max(1000, int(base * scale))


def box_bunny() -> tuple[np.ndarray, np.ndarray]:
    """The default scene's triangles: the paper's closed box with the bunny and the ceiling light."""
    return scene_triangles(SCENES / "bunny_box.xml")


def random_rays(v, n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    return meshes.incoherent_rays(v, n, seed=int(rng.integers(2**31)))


