"""Stock `path`'s estimator (unidirectional path tracing with MIS), every ray through the given queries. Follows
src/integrators/path.cpp @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import (Kinds, Tracing, loop, mis_weight, path_kinds, read_depths,
                                                        skip_area_emitters, unit_throughput)
from layerbvh_mitsuba.runtime.features import Features
from layerbvh_mitsuba.runtime.record import bounce_kind


@dataclass
class PathState:
    """What a path carries from one vertex to the next: the bounce loop's state."""

    ray: mi.Ray3f                      # the ray that found `pi`
    pi: mi.PreliminaryIntersection3f   # the vertex to shade next
    active: mi.Bool
    depth: mi.UInt32
    L: mi.Spectrum                     # radiance so far
    beta: mi.Spectrum                  # throughput
    eta: mi.Float                      # relative index of refraction so far (Russian roulette)
    valid: mi.Bool                     # the sample counts (stock path's valid_ray)
    prev_si: mi.SurfaceInteraction3f   # for the MIS weight of emission found by the BSDF sample
    prev_bsdf_pdf: mi.Float
    prev_bsdf_delta: mi.Bool


class PathEstimator:
    r"""Unidirectional path tracer: the estimator of stock ``path`` (and the primal path of ``prb``).

    Algorithm, per vertex (``vertex``): compute the surface interaction of the current hit, add
    emission with the power-heuristic MIS weight, sample an emitter (``next_2d``, always drawn)
    and test its visibility with an any-hit query, sample the BSDF (``next_1d``, ``next_2d``),
    apply Russian roulette (``next_1d``, always drawn), and find the next hit with a closest-hit
    query. Sampler use is in exactly this order, so a same-seed render matches stock ``path`` up
    to floating-point noise.

    What the feature plan leaves out (no emitter sampling or shadow rays without emitters, no
    emission lookups where nothing hit can emit) changes no image: the samples are still drawn.

    Properties: ``max_depth`` (default -1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false)
    as in ``path``."""

    PLUGIN = "path"     # the stock integrator this mirrors
    VOLUMETRIC = False  # handles participating media (features.plan_features)

    def __init__(self, props: mi.Properties):
        self.max_depth, self.rr_depth, self.hide_emitters = read_depths(props)

    def kinds(self, use: Features) -> Kinds:
        return path_kinds(self.max_depth, use.emitter_sampling.on)

    def auto_rule(self, use: Features) -> str | None:
        """Why every batch of this scene must run per_ray whatever timing says, or None: the path
        tracer times its open decisions."""
        return None

    def sample(self, scene, sampler, ray: mi.Ray3f, medium, active, tr: Tracing):
        """(radiance, valid) of the paths starting with the camera rays `ray`."""
        if self.max_depth == 0:
            return mi.Spectrum(0), mi.Bool(False)
        pi = tr.queries.intersect(ray, active, hint="camera")
        if self.hide_emitters:
            pi = skip_area_emitters(tr.queries, ray, pi, active, tr.megakernel)
        path = self.start(scene, ray, pi, active)
        sampler, path = loop((sampler, path), cond=lambda sampler, path: path.active,
                             body=lambda sampler, path: self.vertex(scene, sampler, tr, path),
                             symbolic=tr.megakernel, label="layerbvh path tracer")
        return dr.select(path.valid, path.L, 0), path.valid

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass on camera rays `cam`: their hits and one path vertex (every kind of
        batch a render traces)."""
        active = dr.full(mi.Bool, True, dr.width(cam.o))
        self.vertex(scene, sampler, tr, self.start(scene, cam, tr.queries.intersect(cam, active, hint="camera"),
                                                    active))

    def start(self, scene, ray: mi.Ray3f, pi, active) -> PathState:
        """The state of paths whose camera rays `ray` found `pi`."""
        n = dr.width(active)
        return PathState(
            ray=ray, pi=pi, active=active, depth=dr.zeros(mi.UInt32, n), L=dr.zeros(mi.Spectrum, n),
            beta=unit_throughput(n), eta=dr.full(mi.Float, 1, n),
            # As in stock `path`: a path that only sees the environment is a valid sample.
            valid=dr.full(mi.Bool, (not self.hide_emitters) and scene.environment() is not None, n),
            prev_si=dr.zeros(mi.SurfaceInteraction3f, n), prev_bsdf_pdf=dr.full(mi.Float, 1, n),
            prev_bsdf_delta=dr.full(mi.Bool, True, n))

    def vertex(self, scene, sampler, tr: Tracing, p: PathState):
        """One loop iteration: shade the vertex `p.pi`, then find the next one."""
        tr.iteration()
        use, queries = tr.use, tr.queries
        bsdf_ctx = mi.BSDFContext()
        active, depth, beta, eta = p.active, p.depth, p.beta, p.eta
        si = queries.surface(p.pi, p.ray, mi.RayFlags.All, active)
        bsdf = si.bsdf(p.ray)
        active_next = mi.Bool(active)
        if self.hide_emitters:
            active_next &= ~((depth == 0) & ~si.is_valid())

        # Emission reached by the previous BSDF sample, MIS-weighted against emitter sampling.
        Le = mi.Spectrum(0)
        if use.emitter_hits.on:
            ds = mi.DirectionSample3f(scene, si=si, ref=p.prev_si)
            mis = mis_weight(p.prev_bsdf_pdf, scene.pdf_emitter_direction(p.prev_si, ds, ~p.prev_bsdf_delta))
            Le = beta * mis * ds.emitter.eval(si, active_next & (p.prev_bsdf_pdf > 0))

        if self.max_depth >= 0:
            active_next &= depth + 1 < self.max_depth
        active_next &= si.is_valid()

        # Emitter sampling; Mitsuba's own visibility test would trace with Embree, so it is
        # switched off and the shadow ray goes through our any-hit query.
        # The sample is drawn even when emitter sampling is left out: the sequence stays stock's.
        em_sample = sampler.next_2d()
        Lr_dir = mi.Spectrum(0)
        if use.emitter_sampling.on:
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, em_sample, False, active_em)
            active_em &= ds.pdf != 0.0
            active_em &= ~queries.occluded(queries.shadow_ray(si, ds.p), active_em)
            wo = si.to_local(ds.d)
            bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
            bsdf_value_em = si.to_world_mueller(bsdf_value_em, -wo, si.wi)  # (polarized: into world frames)
            mis_em = dr.select(ds.delta, 1, mis_weight(ds.pdf, bsdf_pdf_em))
            Lr_dir = dr.select(active_em, beta * mis_em * bsdf_value_em * em_weight, 0)

        bsdf_sample, bsdf_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi)

        # (Without either emission term L stays p.L itself: Dr.Jit's loop optimisation re-records
        # a loop whose state comes back unchanged, and `select(active, 0 + 0, 0)` on the literal
        # it then substitutes is a new variable, which it refuses.)
        L = dr.select(active, p.L + Le + Lr_dir, p.L) if use.emitter_hits.on or use.emitter_sampling.on else p.L
        ray = queries.spawn(si, si.to_world(bsdf_sample.wo))
        eta = dr.select(active, eta * bsdf_sample.eta, eta)
        beta = dr.select(active, beta * bsdf_weight, beta)
        valid = p.valid | (active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Null))

        # Stock `path` counts the vertex before deciding Russian roulette on the new depth.
        depth = dr.select(active & si.is_valid(), depth + 1, depth)
        beta_max = dr.max(mi.unpolarized_spectrum(beta))
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = depth >= self.rr_depth
        beta = dr.select(active & rr_active, beta * dr.rcp(rr_prob), beta)
        rr_continue = sampler.next_1d() < rr_prob
        active = active_next & (~rr_active | rr_continue) & (beta_max != 0)

        kind = bounce_kind(mi, dr, bsdf_sample.sampled_type, p.depth) if tr.recording else None
        pi = queries.intersect(ray, active, hint="bounce", kind=kind)
        return sampler, PathState(ray=ray, pi=pi, active=active, depth=depth, L=L, beta=beta, eta=eta, valid=valid,
                                  prev_si=si, prev_bsdf_pdf=bsdf_sample.pdf,
                                  prev_bsdf_delta=mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta))

    def describe(self) -> str:
        return f"max_depth={self.max_depth}, rr_depth={self.rr_depth}"
