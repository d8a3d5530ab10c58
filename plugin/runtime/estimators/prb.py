"""Stock `prb`'s estimator (path replay backpropagation: a path tracer with MIS whose paths are traced again for
their derivatives), every ray query ours. Follows mitsuba/python/ad/integrators/prb.py @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import (Kinds, Tracing, loop, mis_weight, read_ad_depths, vertex_limit,
                                                        visible_emitter_sample)
from layerbvh_mitsuba.runtime.estimators.replay import (PathReplay, area_jacobian, camera_hits, differential, propagate,
                                                        reattached_reflection)
from layerbvh_mitsuba.runtime.features import Features
from layerbvh_mitsuba.runtime.record import bounce_kind


@dataclass
class ReplayState(PathReplay):
    """What a replayed prb path carries besides PathReplay's: the previous vertex's BSDF sample
    (for the MIS weight of emission it finds) and the index of refraction (Russian roulette)."""

    si_prev: mi.SurfaceInteraction3f       # the previous vertex, detached
    bsdf_pdf_prev: mi.Float
    bsdf_delta_prev: mi.Bool
    eta: mi.Float                          # relative index of refraction so far


def _textured_area_emitters(scene) -> bool:
    """Whether an emitter is a surface whose emission varies over it: only then does a replayed
    emitter sample need the emitter's own surface interaction (and a ray query to find it)."""
    return any(mi.has_flag(e.flags(), mi.EmitterFlags.Surface)
               and mi.has_flag(e.flags(), mi.EmitterFlags.SpatiallyVarying) for e in scene.emitters())


class PRBEstimator:
    r"""Path replay backpropagation: the estimator of stock ``prb`` (an ``RBIntegrator``).

    The render driver runs it as Mitsuba's ``RBIntegrator`` does: once in primal mode (the
    image, and each path's radiance ``L``), then, for a gradient, once more at the same seed in
    forward or backward mode, which replays every path from its camera ray with ``L`` as the
    radiance still to come and, per vertex, attaches the derivatives of what the vertex adds
    (emission, the emitter sample, the reflected rest of ``L``) and pushes them forward into
    ``dL`` or back from the adjoint image into the parameters' gradients.

    Per vertex (``vertex``): the surface interaction (with derivatives when replaying, and wi
    turned by the previous vertex's motion), emission found by the previous BSDF sample with its
    power-heuristic MIS weight, an emitter sample (``next_2d``; its visibility our any-hit
    query; when replaying, its value, direction and Jacobian re-attached, the emitter's own
    surface found by our closest-hit query where emission is textured), the BSDF sample
    (``next_1d``, ``next_2d``: Python evaluates arguments left to right), Russian roulette from
    ``rr_depth`` (``next_1d``, always drawn, survival ``min(max(beta) eta^2, 0.95)``), and the
    next vertex by our closest-hit query. Sampler use is in exactly this order, so a same-seed
    render and its gradients match stock ``prb``'s up to floating-point noise.

    Properties: ``max_depth`` (default 6, -1 infinite), ``rr_depth`` (5), ``hide_emitters``
    (false), as in ``prb``."""

    PLUGIN = "prb"            # the stock integrator this mirrors
    VOLUMETRIC = False
    DIFFERENTIABLE = True     # the driver is an RBIntegrator: `sample` takes an AD mode
    FORWARD = True            # forward-mode derivatives as well as backward
    NEXT_FLAGS = mi.RayFlags.Minimal  # what the replay computes of the next vertex

    def __init__(self, props: mi.Properties):
        self.max_depth, self.rr_depth, self.hide_emitters = read_ad_depths(props)
        self.vertices = vertex_limit(self.max_depth)

    def kinds(self, use: Features) -> Kinds:
        """Camera and bounce rays (every vertex traces its next ray), shadow rays where it samples emitters."""
        return [(False, "camera"), (False, "bounce")] + ([(True, "shadow")] if use.emitter_sampling.on else [])

    def auto_rule(self, use: Features) -> str | None:
        return None

    def sample(self, mode, scene, sampler, ray: mi.Ray3f, dL, state_in, active, tr: Tracing):
        """(L or dL, valid, aovs, L) of the paths starting with camera rays `ray`, in AD `mode`
        (Mitsuba's ADIntegrator.sample)."""
        # As stock prb (prb.py @ v3.9.1: `ray = mi.Ray3f(dr.detach(ray))`; prb_basic and
        # prbvolpath keep the ray as given). Not observable through mi.render, which samples camera
        # rays under dr.suspend_grad; a direct sample() with a differentiable camera ray fails on
        # stock itself (prb: "not attached to the AD graph"; prb_basic: ad_traverse in forward mode).
        ray = mi.Ray3f(dr.detach(ray))
        state = self.start(mode, ray, camera_hits(tr, ray, active, self.hide_emitters), active, dL, state_in)
        textured = _textured_area_emitters(scene)
        sampler, state = loop((sampler, state), cond=lambda sampler, s: s.active,
                              body=lambda sampler, s: self.vertex(mode, scene, sampler, tr, s, textured),
                              symbolic=tr.megakernel, label=f"layerbvh prb ({mode.name})")
        return (state.dL if differential(mode) else state.L), state.depth != 0, [], state.L

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass on camera rays `cam`: their hits and one primal vertex."""
        active = dr.full(mi.Bool, True, dr.width(cam.o))
        mode = dr.ADMode.Primal
        self.vertex(mode, scene, sampler, tr, self.start(mode, cam, tr.queries.intersect(cam, active), active), False)

    @staticmethod
    def start(mode, ray, pi, active, dL=None, state_in=None) -> ReplayState:
        """The state of paths whose camera rays `ray` found `pi` (`state_in`: the primal pass's L)."""
        n = dr.width(active)
        return ReplayState.begin(mode, ray, pi, active, dL, state_in, si_prev=dr.zeros(mi.SurfaceInteraction3f, n),
                                 bsdf_pdf_prev=dr.full(mi.Float, 1, n), bsdf_delta_prev=dr.full(mi.Bool, True, n),
                                 eta=dr.full(mi.Float, 1, n))

    def vertex(self, mode, scene, sampler, tr: Tracing, s: ReplayState, textured: bool):
        """One loop iteration: shade vertex `s.pi` (and, replaying, push its derivatives), then find the next one."""
        tr.iteration()
        replay = differential(mode)
        ctx = mi.BSDFContext()
        active_next = mi.Bool(s.active)
        si_prev = s.si_prev
        with dr.resume_grad(when=replay):
            si = tr.queries.surface(s.pi, s.ray, mi.RayFlags.All)
            if replay:  # wi follows the previous vertex where it moves (not this one's motion)
                moved = dr.replace_grad(si_prev, tr.queries.surface(s.pi_prev, s.ray_prev, mi.RayFlags.Minimal))
                here = dr.detach(si)
                later = s.depth >= 1
                si.wi = dr.select(later, dr.replace_grad(si.wi, here.to_local(dr.normalize(moved.p - here.p))), si.wi)
                si_prev = dr.select(later, moved, si_prev)
        bsdf = si.bsdf(s.ray)
        if self.hide_emitters:
            active_next &= ~((s.depth == 0) & ~si.is_valid())

        # Emission found by the previous BSDF sample, MIS-weighted against emitter sampling.
        ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
        mis = dr.detach(mis_weight(s.bsdf_pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~s.bsdf_delta_prev)))
        with dr.resume_grad(when=replay):
            Le = s.beta * mis * ds.emitter.eval(si, active_next)

        active_next &= (s.depth + 1 < self.vertices) & si.is_valid()
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_weight = visible_emitter_sample(scene, tr.queries, si, sampler.next_2d(), active_em,
                                               test=tr.use.emitter_sampling.on)
        active_em &= ds.pdf != 0
        with dr.resume_grad(when=replay):
            if replay:
                ds, em_weight = self._reattached_emitter_sample(scene, tr, si, ds, em_weight, active_em, textured)
            bsdf_value_em, bsdf_pdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
            mis_em = dr.select(ds.delta, 1, dr.detach(mis_weight(ds.pdf, bsdf_pdf_em)))
            Lr_dir = s.beta * mis_em * bsdf_value_em * em_weight

        bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), active_next)
        L = s.L - Le - Lr_dir if replay else s.L + Le + Lr_dir
        ray_next = tr.queries.spawn(si, si.to_world(bs.wo))
        eta = s.eta * bs.eta
        beta = s.beta * bsdf_weight

        # Russian roulette on the throughput so far (stock decides it on the depth before this vertex counts).
        beta_max = dr.max(mi.unpolarized_spectrum(beta))
        active_next &= beta_max != 0
        rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
        rr_active = s.depth >= self.rr_depth
        beta = dr.select(rr_active, beta * dr.rcp(rr_prob), beta)
        active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

        kind = bounce_kind(mi, dr, bs.sampled_type, s.depth) if tr.recording else None
        pi_next = tr.queries.intersect(ray_next, active_next, hint="bounce", kind=kind)
        dL = s.dL
        if replay:
            Lr_ind = reattached_reflection(tr.queries, L, si, bsdf, ray_next, pi_next, active_next, self.NEXT_FLAGS)
            with dr.resume_grad():
                dL = propagate(mode, dL, Le + Lr_dir + Lr_ind, s.active, tr.megakernel)

        # In the wavefront loop every lane runs the body: paths that ended keep their state.
        new = ReplayState(ray=ray_next, pi=pi_next, ray_prev=s.ray, pi_prev=s.pi, si_prev=dr.detach(si, True),
                          bsdf_pdf_prev=bs.pdf, bsdf_delta_prev=mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta),
                          active=active_next, depth=dr.select(si.is_valid(), s.depth + 1, s.depth), L=L, dL=dL,
                          beta=beta, eta=eta)
        return sampler, dr.select(s.active, new, s)

    @staticmethod
    def _reattached_emitter_sample(scene, tr: Tracing, si, ds, em_weight, active_em, textured: bool):
        """The detached emitter sample `ds` with its derivatives attached (under dr.resume_grad):
        its position and direction (on a textured area emitter from the emitter's own surface
        interaction, found by our closest-hit query past the sampled point), the emitter's value
        re-evaluated over the detached pdf, and the Jacobian of a moving vertex."""
        flags = ds.emitter.flags()
        is_surface = mi.has_flag(flags, mi.EmitterFlags.Surface)
        is_infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)
        textured_em = active_em & is_surface & mi.has_flag(flags, mi.EmitterFlags.SpatiallyVarying)
        if textured:
            ray_em = tr.queries.shadow_ray(si, ds.p)
            ray_em.o = dr.fma(ray_em.d, ray_em.maxt, ray_em.o)  # (visibility is already known)
            ray_em.maxt = dr.largest(ray_em.maxt)
            pi_em = tr.queries.intersect(dr.detach(ray_em), textured_em, hint="bounce")
            si_em = tr.queries.surface(pi_em, ray_em, mi.RayFlags.All, textured_em)
        else:  # (no emitter is textured: the mask is empty)
            si_em = dr.zeros(mi.SurfaceInteraction3f, dr.width(active_em))
        ds_diff = dr.select(textured_em, mi.DirectionSample3f(scene, si_em, si), dr.zeros(mi.DirectionSample3f))
        ds_diff.d = dr.select(textured_em, ds_diff.d, dr.normalize(ds.p - si.p))
        ds_diff.d = dr.select(~is_infinite, ds_diff.d, ds.d)
        ds = dr.replace_grad(ds, ds_diff)
        J = area_jacobian(si.p, dr.detach(ds.p), dr.detach(ds.n), active_em & is_surface)
        value = scene.eval_emitter_direction(si, ds, active_em)
        inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
        return ds, dr.replace_grad(em_weight, value * dr.detach(inv_pdf)) * dr.relative_grad(J)

    def describe(self) -> str:
        return f"max_depth={self.max_depth}, rr_depth={self.rr_depth}"
