"""Stock `prb_basic`'s estimator (path replay backpropagation without emitter sampling, MIS or Russian roulette),
every ray query ours. Follows mitsuba/python/ad/integrators/prb_basic.py @ v3.9.1."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import Kinds, Tracing, loop, read_ad_depths, vertex_limit
from layerbvh_mitsuba.runtime.estimators.replay import (PathReplay, camera_hits, differential, propagate,
                                                        reattached_reflection)
from layerbvh_mitsuba.runtime.features import Features
from layerbvh_mitsuba.runtime.record import bounce_kind


class BasicPRBEstimator:
    r"""Basic path replay backpropagation: the estimator of stock ``prb_basic``, a path tracer that
    finds emission only where its BSDF-sampled rays hit it (no emitter sampling, no MIS, no
    Russian roulette), and replays each path for its derivatives as ``prb`` does
    (``estimators/prb.py`` says how the driver runs the two passes).

    Per vertex (``vertex``): the surface interaction (with derivatives when replaying, wi turned
    by the previous vertex's motion), its emission, the BSDF sample (``next_1d``, ``next_2d``:
    the only draws), and the next vertex by our closest-hit query; a path stops at ``max_depth``
    vertices or where its throughput is 0. Replaying, the emission and the reflected rest of the
    path's radiance are pushed forward or back.

    Properties: ``max_depth`` (default 6, -1 infinite), ``hide_emitters`` (false), as in
    ``prb_basic`` (which reads ``rr_depth`` and does not use it)."""

    PLUGIN = "prb_basic"
    VOLUMETRIC = False
    DIFFERENTIABLE = True
    FORWARD = True            # forward-mode derivatives as well as backward
    NEXT_FLAGS = mi.RayFlags.All  # what the replay computes of the next vertex

    def __init__(self, props: mi.Properties):
        self.max_depth, self.rr_depth, self.hide_emitters = read_ad_depths(props)
        self.vertices = vertex_limit(self.max_depth)

    def kinds(self, use: Features) -> Kinds:
        return [(False, "camera"), (False, "bounce")]

    def auto_rule(self, use: Features) -> str | None:
        return None

    def sample(self, mode, scene, sampler, ray: mi.Ray3f, dL, state_in, active, tr: Tracing):
        """(L or dL, valid, aovs, L) of the paths starting with camera rays `ray`, in AD `mode`."""
        state = PathReplay.begin(mode, ray, camera_hits(tr, ray, active, self.hide_emitters), active, dL, state_in)
        sampler, state = loop((sampler, state), cond=lambda sampler, s: s.active,
                              body=lambda sampler, s: self.vertex(mode, scene, sampler, tr, s),
                              symbolic=tr.megakernel, label=f"layerbvh prb_basic ({mode.name})")
        return (state.dL if differential(mode) else state.L), state.depth != 0, [], state.L

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass on camera rays `cam`: their hits and one primal vertex."""
        active = dr.full(mi.Bool, True, dr.width(cam.o))
        mode = dr.ADMode.Primal
        self.vertex(mode, scene, sampler, tr, PathReplay.begin(mode, cam, tr.queries.intersect(cam, active), active))

    def vertex(self, mode, scene, sampler, tr: Tracing, s: PathReplay):
        """One loop iteration: shade vertex `s.pi` (and, replaying, push its derivatives), then find the next one."""
        tr.iteration()
        replay = differential(mode)
        active_next = mi.Bool(s.active)
        with dr.resume_grad(when=replay):
            si = tr.queries.surface(s.pi, s.ray, mi.RayFlags.All)
            if replay:  # wi follows the previous vertex where it moves (not this one's motion)
                prev = tr.queries.surface(s.pi_prev, s.ray_prev, mi.RayFlags.All)
                here = dr.detach(si)
                si.wi = dr.select(s.depth >= 1, dr.replace_grad(si.wi, here.to_local(dr.normalize(prev.p - here.p))),
                                  si.wi)
        if self.hide_emitters:
            active_next &= ~((s.depth == 0) & ~si.is_valid())
        with dr.resume_grad(when=replay):
            Le = s.beta * si.emitter(scene).eval(si, active_next)
        active_next &= (s.depth + 1 < self.vertices) & si.is_valid()
        bsdf = si.bsdf(s.ray)
        bs, bsdf_weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(), sampler.next_2d(), active_next)
        L = s.L - Le if replay else s.L + Le
        beta = s.beta * bsdf_weight
        active_next &= dr.max(mi.unpolarized_spectrum(beta)) != 0

        ray_next = tr.queries.spawn(si, si.to_world(bs.wo))
        kind = bounce_kind(mi, dr, bs.sampled_type, s.depth) if tr.recording else None
        pi_next = tr.queries.intersect(ray_next, active_next, hint="bounce", kind=kind)
        dL = s.dL
        if replay:
            Lr = reattached_reflection(tr.queries, L, si, bsdf, ray_next, pi_next, active_next, self.NEXT_FLAGS)
            with dr.resume_grad():
                dL = propagate(mode, dL, Le + Lr, s.active, tr.megakernel)

        new = PathReplay(ray=ray_next, pi=pi_next, ray_prev=s.ray, pi_prev=s.pi, active=active_next,
                         depth=dr.select(si.is_valid(), s.depth + 1, s.depth), L=L, dL=dL, beta=beta)
        return sampler, dr.select(s.active, new, s)

    def describe(self) -> str:
        return f"max_depth={self.max_depth}"
