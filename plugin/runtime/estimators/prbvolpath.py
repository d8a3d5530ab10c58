"""Stock `prbvolpath`'s estimator (path replay backpropagation through participating media: free flights, null and
real collisions, surfaces, emitter sampling with ratio-tracked transmittance), every ray query ours. Follows
mitsuba/python/ad/integrators/prbvolpath.py @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import (Kinds, Tracing, loop, mis_weight, read_ad_depths,
                                                        skip_area_emitters, unit_throughput, vertex_limit)
from layerbvh_mitsuba.runtime.estimators.media import MediaWalk, index_spectrum
from layerbvh_mitsuba.runtime.estimators.replay import differential
from layerbvh_mitsuba.runtime.features import Features


@dataclass
class VolumeReplayState:
    """What a replayed volumetric path carries from one loop iteration to the next."""

    active: mi.Bool
    depth: mi.UInt32
    ray: mi.Ray3f
    L: mi.Spectrum                       # radiance: summed (primal), or what remains of it (replay)
    dL: mi.Spectrum                      # the adjoint radiance
    throughput: mi.Spectrum
    eta: mi.Float
    si: mi.SurfaceInteraction3f          # the surface the ray reaches (kept across null collisions)
    needs_intersection: mi.Bool          # `si` is stale: the ray changed since it was found
    last_scatter_event: mi.Interaction3f
    last_scatter_pdf: mi.Float           # the directional pdf of the last real scattering
    medium: mi.MediumPtr
    valid_ray: mi.Bool
    specular_chain: mi.Bool


@dataclass
class NEEState:
    """The emitter sample's transmittance loop."""

    active: mi.Bool
    ray: mi.Ray3f
    total_dist: mi.Float
    si: mi.SurfaceInteraction3f
    needs_intersection: mi.Bool
    medium: mi.MediumPtr
    transmittance: mi.Spectrum


def _push(active, value) -> None:
    """Backpropagate `value` (attached) from the lanes `active` into the parameters' gradients."""
    dr.backward_from(dr.select(active, value, 0))


class PRBVolPathEstimator:
    r"""Volumetric path replay backpropagation: the estimator of stock ``prbvolpath``, backward
    mode only (stock refuses forward mode, and so does this).

    Per loop iteration (``iteration``): Russian roulette from past ``rr_depth`` (``next_1d``,
    survival ``min(max(throughput) eta^2, 0.99)``); in a medium a free flight (``next_1d``) and,
    with heterogeneous media, a null-or-real choice (``next_1d``); the surface reached (our
    closest-hit query; with ``hide_emitters`` a camera ray walks past area emitters); emission
    (MIS against emitter sampling except on camera rays and specular chains); an emitter sample
    (``next_2d``) whose transmittance a loop of our closest-hit queries ratio-tracks through
    media and null surfaces (``next_1d`` per step in a medium); phase sampling (``next_1d``,
    ``next_2d``) or BSDF sampling (``next_1d``, ``next_2d``). The colour channel that drives
    free flights is drawn first in RGB variants (``next_1d``). Replaying, each weight's
    derivative is pushed back from the adjoint radiance; the emitter sample is drawn again
    from a copy of the sampler for its derivatives, as stock does.

    Properties: ``max_depth`` (default 6, -1 infinite), ``rr_depth`` (5), ``hide_emitters`` (false)."""

    PLUGIN = "prbvolpath"
    VOLUMETRIC = True
    DIFFERENTIABLE = True
    FORWARD = False  # (stock's refuses forward mode)

    def __init__(self, props: mi.Properties):
        if mi.is_polarized:
            # Stock's fails at its first Russian roulette there: `dr.any(throughput != 0)` of a Mueller
            # matrix reduces one axis only, and `next_1d` refuses the mask that leaves (a TypeError).
            raise ValueError(f"prbvolpath does not run in polarized variants (stock's fails there); the active "
                             f"variant is {mi.variant()}")
        self.max_depth, self.rr_depth, self.hide_emitters = read_ad_depths(props)
        self.vertices = vertex_limit(self.max_depth)

    def kinds(self, use: Features) -> Kinds:
        """Camera and bounce rays; emitter samples step through the scene with closest-hit queries."""
        return [(False, "camera"), (False, "bounce"), (False, "shadow")]

    def auto_rule(self, use: Features) -> str | None:
        return MediaWalk.auto_rule(self, use)  # (volpath's rule: it reads only the plan)

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass: the first two loop iterations of the camera rays `cam`."""
        mode, media = dr.ADMode.Primal, self._media(scene)
        s, channel = self.start(mode, sampler, cam, dr.full(mi.Bool, True, dr.width(cam.o)))
        for _ in range(2):
            sampler, s = self.iteration(mode, scene, sampler, tr, s, channel, media)

    @staticmethod
    def _media(scene) -> tuple[bool, bool]:
        """(a homogeneous medium, a heterogeneous one) on the scene's shapes: stock's
        `prepare_scene` (which keeps its first scene's answer; this asks each scene)."""
        media = [m for s in scene.shapes() for m in (s.interior_medium(), s.exterior_medium()) if m is not None]
        return any(m.is_homogeneous() for m in media), any(not m.is_homogeneous() for m in media)

    def sample(self, mode, scene, sampler, ray: mi.Ray3f, dL, state_in, active, tr: Tracing):
        """(L or dL, valid, aovs, L) of the paths starting with camera rays `ray`, in AD `mode`."""
        if mode == dr.ADMode.Forward:
            raise RuntimeError("layerbvh_prbvolpath, as prbvolpath, does not support forward-mode differentiation")
        media = self._media(scene)
        s, channel = self.start(mode, sampler, ray, active, dL, state_in)
        sampler, s = loop((sampler, s), cond=lambda sampler, s: s.active,
                          body=lambda sampler, s: self.iteration(mode, scene, sampler, tr, s, channel, media),
                          symbolic=tr.megakernel, label=f"layerbvh prbvolpath ({mode.name})")
        return (s.dL if differential(mode) else s.L), s.valid_ray, [], s.L

    def start(self, mode, sampler, ray, active, dL=None, state_in=None):
        """The loop's first state (the sensor is outside any medium, as in stock) and the colour
        channel that drives free flights."""
        n = dr.width(active)
        channel = mi.UInt32(0)
        if mi.is_rgb:
            channels = dr.size_v(mi.Spectrum)
            channel = mi.UInt32(dr.minimum(channels * sampler.next_1d(active), channels - 1))
        state = VolumeReplayState(
            active=mi.Bool(active), depth=dr.zeros(mi.UInt32, n), ray=mi.Ray3f(ray),
            L=dr.zeros(mi.Spectrum, n) if not differential(mode) else mi.Spectrum(state_in),
            dL=dr.zeros(mi.Spectrum, n) if dL is None else mi.Spectrum(dL), throughput=unit_throughput(n),
            eta=dr.full(mi.Float, 1, n), si=dr.zeros(mi.SurfaceInteraction3f, n),
            needs_intersection=dr.full(mi.Bool, True, n), last_scatter_event=dr.zeros(mi.Interaction3f, n),
            last_scatter_pdf=dr.full(mi.Float, 1, n), medium=dr.zeros(mi.MediumPtr, n),
            valid_ray=dr.full(mi.Bool, False, n), specular_chain=dr.full(mi.Bool, True, n))
        return state, channel

    def _hit(self, tr: Tracing, ray, si, intersect, hint: str):
        """`si` where `intersect` replaced by the closest hit of `ray` (stock's scene.ray_intersect)."""
        return dr.select(intersect, MediaWalk.hit(tr.queries, ray, intersect, hint), si)

    def iteration(self, mode, scene, sampler, tr: Tracing, s: VolumeReplayState, channel, media):
        tr.iteration()
        replay = differential(mode)
        homogeneous, null_scattering = media
        depth, ray, L, dL, throughput, eta = s.depth, mi.Ray3f(s.ray), s.L, s.dL, s.throughput, s.eta
        si, needs_intersection = s.si, s.needs_intersection
        last_event, last_pdf = s.last_scatter_event, s.last_scatter_pdf
        medium, valid_ray, specular_chain = s.medium, s.valid_ray, s.specular_chain
        hint = "camera" if tr.iterations <= 1 and not tr.megakernel else "bounce"
        active = s.active & dr.any(throughput != 0)

        q = dr.minimum(dr.max(throughput) * dr.square(eta), 0.99)
        perform_rr = depth > self.rr_depth
        active &= (sampler.next_1d(active) < q) | ~perform_rr
        throughput = dr.select(perform_rr, throughput * dr.rcp(q), throughput)
        active_medium = active & (medium != None)  # noqa: E711
        active_surface = active & ~active_medium

        with dr.resume_grad(when=replay):
            # A free flight in the ray's medium, and the surface it reaches.
            mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
            mei.t = dr.detach(mei.t)
            ray.maxt = dr.select(active_medium & medium.is_homogeneous() & mei.is_valid(), mei.t, ray.maxt)
            intersect = needs_intersection & active_medium
            si = self._hit(tr, ray, si, intersect, hint)
            needs_intersection &= ~active_medium
            mei.t = dr.select(active_medium & (si.t < mei.t), dr.inf, mei.t)
            tr_, free_flight_pdf = medium.transmittance_eval_pdf(mei, si, active_medium)
            tr_pdf = index_spectrum(free_flight_pdf, channel)
            weight = dr.select(active_medium, dr.select(tr_pdf > 0, tr_ / dr.detach(tr_pdf), 0), mi.Spectrum(1))
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            if null_scattering:
                scatter_prob = dr.mean(mei.sigma_t / mei.combined_extinction)
                null = (sampler.next_1d(active_medium) >= scatter_prob) & active_medium
                act_medium_scatter = ~null & active_medium
                weight = dr.select(null, weight * mei.sigma_n / dr.detach(1 - scatter_prob), weight)
            else:
                scatter_prob, act_medium_scatter = mi.Float(1), active_medium
            depth = dr.select(act_medium_scatter, depth + 1, depth)
            last_event = dr.select(act_medium_scatter, dr.detach(mi.Interaction3f(mei)), last_event)
            active &= depth < self.vertices
            act_medium_scatter &= active
            if null_scattering:
                ray.o = dr.select(null, dr.detach(mei.p), ray.o)
                si.t = dr.select(null, si.t - dr.detach(mei.t), si.t)
            weight = dr.select(act_medium_scatter, weight * mei.sigma_s / dr.detach(scatter_prob), weight)
            throughput *= dr.detach(weight)
            mei = dr.detach(mei)
            if replay and dr.grad_enabled(weight):
                rest = dr.detach(dr.select(active_medium | escaped_medium, L / dr.maximum(1e-8, weight), 0))
                _push(s.active, dL * weight * rest)
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = dr.select(act_medium_scatter, mei.medium.phase_function(), dr.zeros(mi.PhaseFunctionPtr))

            # The surface a path reaches, and its emission.
            active_surface |= escaped_medium
            intersect = active_surface & needs_intersection
            si = self._hit(tr, ray, si, intersect, hint)
            if self.hide_emitters:
                skip = si.is_valid() & (si.shape.emitter() != None) & (depth == 0) & intersect  # noqa: E711
                behind = tr.queries.spawn(si, ray.d)
                pi = skip_area_emitters(tr.queries, behind, tr.queries.intersect(behind, skip, hint=hint), skip,
                                        tr.megakernel)
                si = dr.select(skip, tr.queries.surface(pi, ray, mi.RayFlags.All, skip), si)
            count_direct = (active_surface & (depth == 0)) | specular_chain
            emitter = si.emitter(scene)
            active_e = active_surface & (emitter != None) & ~((depth == 0) & self.hide_emitters)  # noqa: E711
            ds = mi.DirectionSample3f(scene, si, last_event)
            emitter_pdf = scene.pdf_emitter_direction(last_event, ds, active_e)
            emitted = emitter.eval(si, active_e)
            contrib = dr.select(count_direct, throughput * emitted,
                                throughput * dr.detach(mis_weight(last_pdf, emitter_pdf)) * emitted)
            L = dr.select(active_e, L + dr.detach(-contrib if replay else contrib), L)
            if replay and dr.grad_enabled(contrib):
                _push(s.active, dL * contrib)
            active_surface &= si.is_valid()
            ctx = mi.BSDFContext()
            bsdf = si.bsdf(ray)

            # Emitter sampling from the surface or the medium, through media and null surfaces.
            active_e_surface = (active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
                                & (depth + 1 < self.vertices))
            sample_emitters = mei.medium.use_emitter_sampling()
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters
            active_e_medium = act_medium_scatter & sample_emitters
            active_e = active_e_surface | active_e_medium
            nee_sampler = sampler.clone() if replay else sampler
            args = (mei, si, active_e_medium, active_e_surface, scene, tr, medium, channel, active_e, homogeneous)
            emitted, ds = self.sample_emitter(*args, sampler, dr.ADMode.Primal)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_e_surface)
            phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active_e_medium)
            nee_weight = dr.select(active_e_surface, bsdf_val, phase_val)
            nee_pdf = dr.select(ds.delta, 0.0, dr.select(active_e_surface, bsdf_pdf, phase_pdf))
            contrib = throughput * nee_weight * dr.detach(mis_weight(ds.pdf, nee_pdf)) * emitted
            L = dr.select(active_e, L + dr.detach(-contrib if replay else contrib), L)
            if replay:
                self.sample_emitter(*args, nee_sampler, mode, adj_emitted=contrib, dL=dL)
                if dr.grad_enabled(nee_weight) or dr.grad_enabled(emitted):
                    _push(s.active, dL * contrib)

            # Phase function sampling.
            valid_ray |= act_medium_scatter
            with dr.suspend_grad():
                wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sampler.next_1d(act_medium_scatter),
                                                           sampler.next_2d(act_medium_scatter), act_medium_scatter)
            act_medium_scatter &= phase_pdf > 0
            phase_eval, _ = phase.eval_pdf(phase_ctx, mei, wo, act_medium_scatter)
            if replay and dr.grad_enabled(phase_eval):
                _push(s.active, dL * phase_eval * dr.detach(
                    dr.select(act_medium_scatter, L / dr.maximum(1e-8, phase_eval), 0)))
            throughput = dr.select(act_medium_scatter, throughput * phase_weight, throughput)
            ray = dr.select(act_medium_scatter, mei.spawn_ray(wo), ray)
            needs_intersection |= act_medium_scatter
            last_pdf = dr.select(act_medium_scatter, phase_pdf, last_pdf)

            # BSDF sampling.
            with dr.suspend_grad():
                bs, bsdf_weight = bsdf.sample(ctx, si, sampler.next_1d(active_surface), sampler.next_2d(active_surface),
                                              active_surface)
                active_surface &= bs.pdf > 0
            bsdf_eval = bsdf.eval(ctx, si, bs.wo, active_surface)
            if replay and dr.grad_enabled(bsdf_eval):
                _push(s.active, dL * bsdf_eval * dr.detach(
                    dr.select(active_surface, L / dr.maximum(1e-8, bsdf_eval), 0)))
            throughput = dr.select(active_surface, throughput * bsdf_weight, throughput)
            eta = dr.select(active_surface, eta * bs.eta, eta)
            ray = dr.select(active_surface, tr.queries.spawn(si, si.to_world(bs.wo)), ray)
            needs_intersection |= active_surface
            non_null = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth = dr.select(non_null, depth + 1, depth)
            last_event = dr.select(non_null, mi.Interaction3f(si), last_event)
            last_pdf = dr.select(non_null, bs.pdf, last_pdf)
            valid_ray |= non_null
            specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
            active &= active_surface | active_medium

        new = VolumeReplayState(active=active, depth=depth, ray=ray, L=L, dL=dL, throughput=throughput, eta=eta,
                                si=si, needs_intersection=needs_intersection, last_scatter_event=last_event,
                                last_scatter_pdf=last_pdf, medium=medium, valid_ray=valid_ray,
                                specular_chain=specular_chain)
        return sampler, dr.select(s.active, new, s)

    def sample_emitter(self, mei, si, active_medium, active_surface, scene, tr: Tracing, medium, channel, active,
                       homogeneous: bool, sampler, mode, adj_emitted=None, dL=None):
        """Stock's `sample_emitter`: an emitter sample (``next_2d``) from the medium or surface
        interaction, and its transmittance, ratio-tracked by a loop of our closest-hit queries
        through media (``next_1d`` per step in one; a homogeneous one crossed analytically) and
        null surfaces. Replaying (`mode` not primal), the transmittance's derivatives are pushed
        back from `adj_emitted`, the contribution it scaled. Returns (the emitter's value times the
        transmittance, detached; the sample)."""
        replay = differential(mode)
        ref = dr.zeros(mi.Interaction3f, dr.width(active))
        ref = dr.select(active_medium, mi.Interaction3f(mei), ref)
        ref = dr.select(active_surface, mi.Interaction3f(si), ref)
        ds, emitter_val = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        ds = dr.detach(ds)
        invalid = ds.pdf == 0
        emitter_val = dr.select(invalid, 0, emitter_val)
        active = active & ~invalid
        medium = dr.select(active, medium, dr.zeros(mi.MediumPtr))
        medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ds.d), medium)
        ray = tr.queries.shadow_ray(ref, ds.p)
        max_dist = mi.Float(ray.maxt)
        n = dr.width(active)
        state = NEEState(active=active, ray=ray, total_dist=dr.zeros(mi.Float, n),
                         si=dr.zeros(mi.SurfaceInteraction3f, n), needs_intersection=dr.full(mi.Bool, True, n),
                         medium=medium, transmittance=unit_throughput(n))

        def step(sampler, t: NEEState):
            active, ray, si, medium = mi.Bool(t.active), mi.Ray3f(t.ray), t.si, t.medium
            remaining = max_dist - t.total_dist
            ray.maxt = dr.detach(remaining)
            active &= remaining > 0
            needs = t.needs_intersection & active
            si = self._hit(tr, ray, si, needs, "shadow")
            active_medium = active & (medium != None)  # noqa: E711
            active_surface = active & ~active_medium
            m = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
            m.t = dr.detach(dr.select(active_medium & (si.t < m.t), dr.inf, m.t))
            tr_mult = mi.Spectrum(1)
            if homogeneous:  # (crossed in one step: its transmittance to the next surface or the emitter)
                homo = active_medium & medium.is_homogeneous()
                m.t = dr.select(homo, dr.minimum(remaining, si.t), m.t)
                tr_mult = dr.select(homo, medium.transmittance_eval_pdf(m, si, homo)[0], tr_mult)
                m.t = dr.select(homo, dr.inf, m.t)
            escaped = active_medium & ~m.is_valid()
            active_medium &= m.is_valid()
            ray.o = dr.select(active_medium, dr.detach(m.p), ray.o)
            si.t = dr.select(active_medium, dr.detach(si.t - m.t), si.t)
            tr_mult = dr.select(active_medium, tr_mult * m.sigma_n / m.combined_extinction, tr_mult)
            active_surface = (active_surface | escaped) & si.is_valid() & ~active_medium
            tr_mult = dr.select(active_surface, tr_mult * si.bsdf(ray).eval_null_transmission(si, active_surface),
                                tr_mult)
            if replay and dr.grad_enabled(tr_mult):
                adj = (active_surface | active_medium) & (tr_mult > 0)
                _push(t.active, tr_mult * dr.detach(dr.select(adj, dL * adj_emitted / tr_mult, 0)))
            transmittance = t.transmittance * dr.detach(tr_mult)
            ray = dr.select(active_surface, dr.detach(tr.queries.spawn(si, mi.Vector3f(ray.d))), ray)
            ray.maxt = dr.detach(remaining)
            active &= (active_medium | active_surface) & dr.any(transmittance != 0)
            total_dist = dr.select(active, t.total_dist + dr.select(active_medium, m.t, si.t), t.total_dist)
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
            new = NEEState(active=active, ray=ray, total_dist=total_dist, si=si,
                           needs_intersection=active_surface, medium=medium, transmittance=transmittance)
            return sampler, dr.select(t.active, new, t)

        sampler, state = loop((sampler, state), cond=lambda sampler, t: t.active, body=step, symbolic=tr.megakernel,
                              label=f"layerbvh prbvolpath emitter sample ({mode.name})")
        return emitter_val * dr.detach(state.transmittance), ds

    def describe(self) -> str:
        return f"max_depth={self.max_depth}, rr_depth={self.rr_depth}"
