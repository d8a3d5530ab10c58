"""What every estimator uses and none owns: the render's tracing context, the loop in either mode, the power
heuristic, stock's depth properties, an emitter sample with our visibility test, and hide_emitters' walk past area
emitters."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.features import Features
from layerbvh_mitsuba.runtime.queries import RayQueries
from layerbvh_mitsuba.runtime.record import RecordingQueries
from layerbvh_mitsuba.runtime.settings import check_depths

Kinds = list[tuple[bool, str]]  # (any_hit, hint) of every kind of ray batch an estimator traces (auto decides per kind)


@dataclass
class Tracing:
    """What the render driver hands an estimator for one render (or for auto's pre-pass): who
    answers its ray queries, the scene's feature plan, and the loop mode (`megakernel`: one
    symbolic Dr.Jit loop; otherwise a Python loop between kernels). The estimator counts its
    loop iterations in `iterations` (wavefront only), which the driver reports."""

    queries: RayQueries
    use: Features
    megakernel: bool
    iterations: int = 0

    @property
    def recording(self) -> bool:
        """A recorder stands in front of the queries: bounce rays get labelled by lobe."""
        return isinstance(self.queries, RecordingQueries)

    def iteration(self) -> None:
        if not self.megakernel:
            self.iterations += 1


def loop(state: tuple, cond, body, symbolic: bool, label: str) -> tuple:
    """`while cond(*state): state = body(*state)`, per lane. Symbolic: one Dr.Jit loop compiled
    into the caller's kernel. Otherwise a Python loop whose body may synchronise with the host
    (our sorted traversal does); its state (a sampler's included) is evaluated after every
    iteration, so every iteration compiles to the same kernels. (Dr.Jit's own evaluated mode
    applies the loop's mask to everything in the body, which arrays of another width, such as
    the traversal's compacted rays, cannot take.)"""
    if symbolic:
        # Polarized variants: a Mueller matrix's entries start as literal zeros and some stay
        # literal through the body, which Dr.Jit's loop optimisation then takes for loop constants
        # and refuses on re-recording ("presumed to be constant, but it changed"; direct's and
        # prb_basic's loops on a dielectric). Without the optimisation, such a loop records once.
        with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, not mi.is_polarized and dr.flag(dr.JitFlag.OptimizeLoops)):
            return dr.while_loop(state, cond, body, label=label, mode="symbolic")
    # The first iteration's state too: a literal in it (dr.zeros, a constant) would be compiled
    # into that iteration's kernels, which the second iteration (evaluated arrays) then compiles
    # again (measured: a volpath case of the stability suite compiled 149 kernels, 3 of most).
    dr.make_opaque(*(x for x in state if not isinstance(x, mi.Sampler)))
    while bool(dr.any(cond(*state), axis=None)):
        state = body(*state)
        for x in state:
            if isinstance(x, mi.Sampler):
                x.schedule_state()
        dr.eval(*(x for x in state if not isinstance(x, mi.Sampler)))
    return state


def unit_throughput(n: int) -> mi.Spectrum:
    """A throughput of 1 on `n` lanes, as stock's `Spectrum throughput(1.f)`: in the polarized
    variants the Mueller identity (`dr.full(mi.Spectrum, 1, n)` would fill all 16 entries with 1,
    which the first column of a Stokes image shows and every polarizing surface then mixes)."""
    return mi.Spectrum(dr.full(mi.Float, 1, n))


def mis_weight(pdf_a, pdf_b):
    """Power heuristic, as in Mitsuba's path tracers."""
    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0)


def read_depths(props: mi.Properties) -> tuple[int, int, bool]:
    """Stock path tracers' `max_depth` (-1: infinite), `rr_depth` (5) and `hide_emitters` (false),
    checked by their one rule (settings.check_depths)."""
    max_depth, rr_depth = props.get("max_depth", -1), props.get("rr_depth", 5)
    check_depths(max_depth, rr_depth)
    return max_depth, rr_depth, props.get("hide_emitters", False)


# Mitsuba's differentiable integrators (ADIntegrator, common.py) default to 6 vertices, not unlimited.
AD_MAX_DEPTH = 6


def read_ad_depths(props: mi.Properties) -> tuple[int, int, bool]:
    """`read_depths` with the differentiable integrators' default max_depth (AD_MAX_DEPTH)."""
    max_depth, rr_depth = props.get("max_depth", AD_MAX_DEPTH), props.get("rr_depth", 5)
    check_depths(max_depth, rr_depth)
    return max_depth, rr_depth, props.get("hide_emitters", False)


def vertex_limit(max_depth: int) -> int:
    """max_depth as the differentiable integrators compare it with a UInt32 depth: -1 (infinite)
    is 2^32 - 1 vertices."""
    return 0xFFFFFFFF if max_depth < 0 else max_depth


def visible_emitter_sample(scene, queries: RayQueries, si, sample, active, test: bool = True):
    """`scene.sample_emitter_direction(si, sample, True, active)` with the visibility test ours:
    as Mitsuba's Scene does it, a sample whose pdf is not 0 is tested, and where it is occluded
    both its weight and its pdf become 0. `test` false leaves the test out (a scene without
    emitters: every pdf is 0). Returns (ds, weight)."""
    ds, weight = scene.sample_emitter_direction(si, sample, False, active)
    if test:
        occluded = queries.occluded(queries.shadow_ray(si, ds.p), mi.Bool(active) & (ds.pdf != 0))
        weight = dr.select(occluded, 0, weight)
        ds.pdf = dr.select(occluded, 0, ds.pdf)
    return ds, weight


def path_kinds(max_depth: int, shadow_rays: bool, shadow_any_hit: bool = True) -> Kinds:
    """The kinds of batch a path of `max_depth` traces: camera rays, bounce rays past the first
    vertex, and shadow rays where it samples emitters (any-hit queries, or closest-hit steps
    where they cross null surfaces and media)."""
    if max_depth == 0:
        return []  # nothing is traced
    kinds = [(False, "camera")]
    if max_depth < 0 or max_depth > 1:
        kinds.append((False, "bounce"))
    if shadow_rays:
        kinds.append((shadow_any_hit, "shadow"))
    return kinds


def skip_area_emitters(queries: RayQueries, ray, pi, active, megakernel: bool):
    """hide_emitters: a camera ray that hits an area emitter continues behind it (as in prb)."""
    def hits_emitter(ray, pi):
        return active & pi.is_valid() & (pi.shape.emitter() != None)  # noqa: E711

    def step(ray, pi):
        hit_em = hits_emitter(ray, pi)
        si = queries.surface(pi, ray, mi.RayFlags.Minimal, hit_em)
        ray = mi.Ray3f(dr.select(hit_em, queries.spawn(si, ray.d).o, ray.o), ray.d)
        return ray, dr.select(hit_em, queries.intersect(ray, hit_em, hint="camera"), pi)
    _, pi = loop((ray, pi), cond=hits_emitter, body=step, symbolic=megakernel, label="layerbvh hide_emitters")
    return pi
