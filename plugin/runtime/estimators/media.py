"""The random walk that stock `volpath` and `volpathmis` share (free flights, null and real collisions, surfaces,
shadow rays through media and null surfaces), with what a path's weight is left to a strategy. Follows
src/integrators/volpath.cpp and volpathmis.cpp @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime import draw_order
from layerbvh_mitsuba.runtime.estimators.common import Kinds, Tracing, loop, path_kinds, read_depths, \
    skip_area_emitters
from layerbvh_mitsuba.runtime.features import Features

UINT32_MAX = 2 ** 32 - 1  # stock keeps max_depth as uint32: -1 (infinite) is this


def index_spectrum(spec, channel):
    """The component `channel` of an unpolarized spectrum in RGB variants (the channel that
    drives free-flight sampling); the first component otherwise, as stock."""
    m = spec[0]
    if mi.is_rgb:
        m = dr.select(channel == 1, spec[1], m)
        m = dr.select(channel == 2, spec[2], m)
    return m


@dataclass
class WalkState:
    """What a path carries from one loop iteration to the next (stock's LoopState), its weight
    in the strategy's own dataclass (`w`)."""

    active: mi.Bool
    depth: mi.UInt32
    ray: mi.Ray3f
    result: mi.Spectrum
    si: mi.SurfaceInteraction3f            # the surface the ray reaches (kept across null scattering)
    mei: mi.MediumInteraction3f
    medium: mi.MediumPtr                   # the medium the ray travels in (null: none)
    eta: mi.Float
    last_scatter_event: mi.Interaction3f   # for the MIS weight of emission found by a sampled direction
    needs_intersection: mi.Bool            # `si` is stale: the ray changed since it was found
    specular_chain: mi.Bool                # only delta events (or scattering without emitter sampling) so far
    valid_ray: mi.Bool
    w: object                              # the path's weight: volpath.Throughput or volpathmis.Ratios


@dataclass
class ShadowState:
    """The transmittance loop's state (stock's `sample_emitter` LoopState)."""

    active: mi.Bool
    ray: mi.Ray3f
    total_dist: mi.Float
    needs_intersection: mi.Bool
    medium: mi.MediumPtr
    si: mi.SurfaceInteraction3f
    weights: object  # what the light carries along the way (the strategy's `shadow` updates it)


class MediaWalk:
    r"""Volumetric path tracing, one loop body for ``volpath`` and ``volpathmis``; `weights` (the
    strategy: volpath.ThroughputWeights, volpathmis.RatioWeights) says what a path's weight is
    and how each event changes it.

    Algorithm (stock ``volpath``'s ``sample``), per loop iteration: Russian roulette on the
    weight (``next_1d``); in a medium, sample a free flight (``next_1d``) along the ray, find the
    surface the ray reaches (a closest-hit query, up to the sampled distance in a homogeneous
    medium) and choose null or real scattering (``next_1d``); at a real scattering event sample
    an emitter (``next_2d``) and estimate the transmittance towards it, then sample the phase
    function (``next_2d``, ``next_1d``); at a surface add the emission found there
    (MIS-weighted against emitter sampling), sample an emitter with transmittance (BSDFs with a
    smooth lobe), sample the BSDF (``next_2d``, ``next_1d``) and switch media where the surface
    is a medium transition. In RGB variants a colour channel that drives free-flight sampling is
    drawn first (``next_1d``). Transmittance towards an emitter is estimated by stepping along
    the shadow ray with closest-hit queries: through null surfaces (their null transmission) and
    media boundaries, with ratio tracking in each medium (``next_1d`` per step). Sampler use is
    in exactly this order and with stock's masks (the 1D and 2D numbers of a BSDF or phase
    sample in the order stock's build evaluates a call's arguments, probed from the wheel:
    runtime/draw_order.py), so a same-seed render matches stock up to floating-point noise.

    The feature plan leaves out what the scene does not need: free-flight sampling when it holds
    no medium, and the closest-hit transmittance steps when it has neither a medium nor a
    null-BSDF surface (a shadow ray is then blocked by its first hit: an any-hit query). Samples
    masked off on every lane change no independent sampler's stream and are not drawn; every
    other sample is drawn as stock draws it.

    Properties: ``max_depth`` (-1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false)."""

    VOLUMETRIC = True

    def __init__(self, props: mi.Properties, weights):
        self.max_depth, self.rr_depth, self.hide_emitters = read_depths(props)
        self.depth_cap = UINT32_MAX if self.max_depth < 0 else self.max_depth
        self.weights = weights

    # -- what the driver asks ---------------------------------------------------------------------
    def kinds(self, use: Features) -> Kinds:
        return path_kinds(self.max_depth, use.emitter_sampling.on, shadow_any_hit=not use.transmittance.on)

    def auto_rule(self, use: Features) -> str | None:
        """Media or null surfaces: the megakernel. Between kernels every null collision and
        every transmittance step is a loop iteration with a host round trip; measured (scripts/
        bench_volpath_loops.py, 48x48, 16 spp) the wavefront loop 7.7x slower than per_ray on
        test_homo_emitter_inside_medium and 126x on test_hetero_sigmat, more than sorting could
        win back on its batches."""
        if use.media.on or use.transmittance.on:
            return ("volpath with media or null surfaces: per_ray in one megakernel (between kernels, "
                    "every null collision and transmittance step costs a host round trip: measured 8-126x "
                    "slower on Mitsuba's media scenes)")
        return None

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass: the first two loop iterations of the camera rays `cam`."""
        s, channel = self.start(scene, sampler, cam, None, dr.full(mi.Bool, True, dr.width(cam.o)))
        for i in range(2):
            sampler, s = self.iteration(scene, sampler, tr, s, channel, "camera" if i == 0 else "bounce")

    def sample(self, scene, sampler, ray: mi.Ray3f, medium, active, tr: Tracing):
        """(radiance, valid) of the paths starting with the camera rays `ray` in `medium`."""
        s, channel = self.start(scene, sampler, ray, medium, active)
        first = [True]

        def body(sampler, s):
            hint = "camera" if first[0] else "bounce"  # (between kernels: the first iteration's rays)
            first[0] = False
            return self.iteration(scene, sampler, tr, s, channel, hint)

        sampler, s = loop((sampler, s), cond=lambda sampler, s: s.active, body=body, symbolic=tr.megakernel,
                          label="layerbvh volpath")
        return s.result, s.valid_ray

    def start(self, scene, sampler, ray: mi.Ray3f, medium, active) -> tuple[WalkState, object]:
        """The loop's first state, and the colour channel that drives free-flight sampling (RGB:
        drawn first, `next_1d`)."""
        n = dr.width(active)
        channel = mi.UInt32(0)
        if mi.is_rgb:
            channels = dr.size_v(mi.Spectrum)
            channel = mi.UInt32(dr.minimum(sampler.next_1d(active) * channels, channels - 1))
        medium = dr.zeros(mi.MediumPtr, n) if medium is None else dr.full(mi.MediumPtr, medium, n)
        state = WalkState(
            active=active, depth=dr.zeros(mi.UInt32, n), ray=ray, result=dr.zeros(mi.Spectrum, n),
            si=dr.zeros(mi.SurfaceInteraction3f, n), mei=dr.zeros(mi.MediumInteraction3f, n), medium=medium,
            eta=dr.full(mi.Float, 1, n), last_scatter_event=dr.zeros(mi.Interaction3f, n),
            needs_intersection=dr.full(mi.Bool, True, n), specular_chain=active & (not self.hide_emitters),
            valid_ray=dr.full(mi.Bool, (not self.hide_emitters) and scene.environment() is not None, n),
            w=self.weights.start(n))
        return state, channel

    # -- the queries ------------------------------------------------------------------------------
    @staticmethod
    def hit(queries, ray: mi.Ray3f, active, hint: str) -> mi.SurfaceInteraction3f:
        """Stock's `scene.ray_intersect`: the closest hit (our traversal), fully interpolated."""
        return queries.surface(queries.intersect(ray, active, hint=hint), ray, mi.RayFlags.All, active)

    def free_flight(self, sampler, queries, ray: mi.Ray3f, si, medium, needs_intersection, active_medium, channel,
                    hint: str, remaining=None):
        """A free flight in the ray's medium (`next_1d`) and the surface it reaches (our closest
        hit, up to the sampled distance in a homogeneous medium, `remaining` at most on a shadow
        ray): (the medium interaction, inf where the surface comes first; the surface; needs_intersection)."""
        mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
        maxt = mei.t if remaining is None else dr.minimum(mei.t, remaining)
        ray.maxt = dr.select(active_medium & medium.is_homogeneous() & mei.is_valid(), maxt, ray.maxt)
        intersect = needs_intersection & active_medium
        si = dr.select(intersect, self.hit(queries, ray, intersect, hint), si)
        needs_intersection &= ~active_medium
        mei.t = dr.select(active_medium & (si.t < mei.t), dr.inf, mei.t)
        return mei, si, needs_intersection

    def emitter_hit(self, scene, si, active_surface, depth, specular_chain, last_event):
        """Emission where a path reaches a surface: (where an emitter is hit, where it counts
        unweighted (camera rays, specular chains), the pdf of emitter sampling having found it
        from the last scattering event, its radiance)."""
        count_direct = (active_surface & (depth == 0)) | specular_chain
        emitter = si.emitter(scene)
        active_e = active_surface & (emitter != None)  # noqa: E711
        if self.hide_emitters:
            active_e &= depth != 0
        ds = mi.DirectionSample3f(scene, si=si, ref=last_event)
        emitter_pdf = scene.pdf_emitter_direction(last_event, ds, active_e)
        return active_e, count_direct, emitter_pdf, emitter.eval(si, active_e)

    def surface_hit(self, queries, ray: mi.Ray3f, si, intersect, depth, hint: str, megakernel: bool):
        """The surface a ray reaches where `intersect` (kept from before elsewhere); with
        hide_emitters a camera ray that hits an area emitter continues behind it (as stock)."""
        si = dr.select(intersect, self.hit(queries, ray, intersect, hint), si)
        if self.hide_emitters:
            skip = si.is_valid() & (si.shape.emitter() != None) & (depth == 0) & intersect  # noqa: E711
            behind = queries.spawn(si, ray.d)
            pi = skip_area_emitters(queries, behind, queries.intersect(behind, skip, hint=hint), skip, megakernel)
            si = dr.select(skip, queries.surface(pi, behind, mi.RayFlags.All, skip), si)
        return si

    # -- one loop iteration -----------------------------------------------------------------------
    def iteration(self, scene, sampler, tr: Tracing, s: WalkState, channel, hint: str):
        tr.iteration()
        W, use, queries, cap = self.weights, tr.use, tr.queries, self.depth_cap
        active, depth, ray, result, w = s.active, s.depth, mi.Ray3f(s.ray), s.result, W.copy(s.w)
        si, mei, medium, eta, last_event = s.si, s.mei, s.medium, s.eta, s.last_scatter_event
        needs_intersection, specular_chain, valid_ray = s.needs_intersection, s.specular_chain, s.valid_ray

        # -- Russian roulette on the weight so far (the strategy's rule), then the depth limit
        active, w = W.roulette(sampler, w, active, depth, eta, self.rr_depth, channel)
        active &= depth < cap

        # -- sampling the RTE in a medium: free flight, then null or real scattering
        active_medium = active & (medium != None)  # noqa: E711  (a Dr.Jit pointer array against null)
        active_surface = active & ~active_medium
        escaped_medium = mi.Bool(False)
        if use.media.on:
            is_spectral = active_medium & medium.has_spectral_extinction()
            not_spectral = ~is_spectral & active_medium
            mei, si, needs_intersection = self.free_flight(sampler, queries, ray, si, medium, needs_intersection,
                                                           active_medium, channel, hint)
            tr_, free_flight_pdf = medium.transmittance_eval_pdf(mei, si, is_spectral)
            w = W.free_flight(w, tr_, free_flight_pdf, channel, is_spectral)
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            is_spectral &= active_medium
            not_spectral &= active_medium

            null_scatter_prob = dr.mean(mei.sigma_n / mei.combined_extinction, axis=0)
            null_scatter = sampler.next_1d(active_medium) < null_scatter_prob
            act_null_scatter = null_scatter & active_medium
            act_medium_scatter = ~act_null_scatter & active_medium
            w = W.null_collision(w, mei, null_scatter_prob, channel, is_spectral & act_null_scatter,
                                 not_spectral & act_null_scatter, act_null_scatter)
            depth = dr.select(act_medium_scatter, depth + 1, depth)
            last_event = dr.select(act_medium_scatter, mi.Interaction3f(mei), last_event)

            # No lighting is estimated beyond the depth limit.
            active &= depth < cap
            act_medium_scatter &= active

            # A null collision moves the ray on; the surface ahead stays the same.
            ray.o = dr.select(act_null_scatter, mei.p, ray.o)
            si.t = dr.select(act_null_scatter, si.t - mei.t, si.t)

            # A real collision scatters: emitter sampling, then phase function sampling.
            w = W.real_collision(w, mei, null_scatter_prob, channel, is_spectral & act_medium_scatter,
                                 not_spectral & act_medium_scatter)
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            sample_emitters = mei.medium.use_emitter_sampling()
            valid_ray |= act_medium_scatter
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters
            active_e = act_medium_scatter & sample_emitters
            if use.emitter_sampling.on:
                shadow_w, emitter_val, ds = self.sample_emitter(mei, False, scene, sampler, tr, medium, channel,
                                                                active_e, w)
                phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active_e)
                result = dr.select(active_e, result + W.direct(w, shadow_w, emitter_val, phase_val, phase_pdf, ds,
                                                               channel, active_e, on_surface=False), result)
            else:
                sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same
            w = W.scattered_in_medium(w, act_medium_scatter)
            phase = dr.select(act_medium_scatter, phase, dr.zeros(mi.PhaseFunctionPtr))
            sample_1, sample_2 = draw_order.draws(sampler, act_medium_scatter)  # (stock's order: class docstring)
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sample_1, sample_2, act_medium_scatter)
            act_medium_scatter, w = W.phase_sampled(w, phase_weight, phase_pdf, channel, act_medium_scatter)
            ray = dr.select(act_medium_scatter, mei.spawn_ray(wo), ray)
            needs_intersection |= act_medium_scatter

        # -- surfaces: the hit, emission found there, emitter sampling, BSDF sampling
        active_surface |= escaped_medium
        intersect = active_surface & needs_intersection
        si = self.surface_hit(queries, ray, si, intersect, depth, hint, tr.megakernel)

        if use.emitter_hits.on:
            active_e, count_direct, emitter_pdf, emitted = self.emitter_hit(scene, si, active_surface, depth,
                                                                            specular_chain, last_event)
            contrib, w = W.surface_emission(w, emitted, emitter_pdf, count_direct, channel, active_e)
            result = dr.select(active_e, result + contrib, result)

        active_surface &= si.is_valid()
        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        active_e = active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < cap)
        if use.emitter_sampling.on:
            shadow_w, emitter_val, ds = self.sample_emitter(si, True, scene, sampler, tr, medium, channel, active_e, w)
            bsdf_val, bsdf_pdf = W.eval_bsdf(bsdf, ctx, si, ds, active_e)
            result = dr.select(active_e, result + W.direct(w, shadow_w, emitter_val, bsdf_val, bsdf_pdf, ds, channel,
                                                           active_e, on_surface=True), result)
        else:
            sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same: the sequence stays stock's

        sample_1, sample_2 = draw_order.draws(sampler, active_surface)
        bs, bsdf_weight = bsdf.sample(ctx, si, sample_1, sample_2, active_surface)
        active_surface, invalid_sample, w = W.bsdf_sampled(w, bs, bsdf_weight, si, channel, active_surface)
        eta = dr.select(active_surface, eta * bs.eta, eta)
        ray = dr.select(active_surface, queries.spawn(si, si.to_world(bs.wo)), ray)
        needs_intersection |= active_surface

        non_null = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        depth = dr.select(non_null, depth + 1, depth)
        last_event = dr.select(non_null, mi.Interaction3f(si), last_event)
        w = W.surface_scattered(w, bs, bsdf_weight, channel, active_surface, non_null)
        valid_ray |= non_null if invalid_sample is None else non_null | invalid_sample
        specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
        if use.media.on:
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
        active &= active_surface | active_medium
        return sampler, WalkState(
            active=active, depth=depth, ray=ray, result=result, si=si, mei=mei, medium=medium, eta=eta,
            last_scatter_event=last_event, needs_intersection=needs_intersection, specular_chain=specular_chain,
            valid_ray=valid_ray, w=w)

    # -- emitter sampling with transmittance ----------------------------------------------------------
    def sample_emitter(self, ref, on_surface: bool, scene, sampler, tr: Tracing, medium, channel, active, w):
        """Stock's `sample_emitter`: an emitter sample from `ref` (a surface or medium interaction),
        the weights the light carries along the shadow ray (the strategy's; None where no walk
        ran: blocked by the first hit), the emitter's value as the strategy takes it, and the
        sample."""
        W = self.weights
        ds, emitter_weight = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        active = active & (ds.pdf != 0)
        emitter_val, shadow_w = W.emitter_start(w, ds, emitter_weight, channel, active)
        ray = tr.queries.shadow_ray(ref, ds.p)
        if not tr.use.transmittance.on:
            # No medium and no null surface: light is blocked by the first hit (stock's loop then
            # ends at its first surface, whose null transmission is zero).
            return shadow_w, dr.select(active & tr.queries.occluded(ray, active), 0, emitter_val), ds
        if on_surface and tr.use.media.on:
            medium = dr.select(ref.is_medium_transition(), ref.target_medium(ray.d), medium)
        return self.shadow_walk(sampler, tr, ray, medium, channel, ds, active, W.shadow_start(shadow_w, active)), \
            emitter_val, ds

    def shadow_walk(self, sampler, tr: Tracing, ray: mi.Ray3f, medium, channel, ds, active, weights):
        """The shadow ray's loop (stock's in `sample_emitter`): step towards the emitter sample
        `ds` until it is reached or no light passes, carrying `weights` as the strategy's
        `shadow` updates them; the weights at the end."""
        max_dist = mi.Float(ray.maxt)
        n = dr.width(active)
        state = ShadowState(active=active, ray=ray, total_dist=dr.zeros(mi.Float, n),
                            needs_intersection=dr.full(mi.Bool, True, n), medium=medium,
                            si=dr.zeros(mi.SurfaceInteraction3f, n), weights=weights)

        def step(sampler, t: ShadowState):
            return sampler, self.transmittance_step(sampler, tr, t, channel, max_dist, ds)

        sampler, state = loop((sampler, state), cond=lambda sampler, t: t.active, body=step, symbolic=tr.megakernel,
                              label="layerbvh volpath transmittance")
        return state.weights

    def transmittance_step(self, sampler, tr: Tracing, t: ShadowState, channel, max_dist, ds) -> ShadowState:
        """One step along a shadow ray: ratio tracking to the next collision in a medium, or the
        next surface, whose null transmission it crosses (a medium boundary switches media)."""
        weigh, use, queries = self.weights.shadow, tr.use, tr.queries
        active, ray, total_dist = t.active, mi.Ray3f(t.ray), t.total_dist
        needs_intersection, medium, si, w = t.needs_intersection, t.medium, t.si, t.weights
        remaining = max_dist - total_dist
        ray.maxt = remaining
        active &= remaining > 0
        active_medium = active & (medium != None)  # noqa: E711
        active_surface = active & ~active_medium
        escaped_medium = mi.Bool(False)
        if use.media.on:
            mei, si, needs_intersection = self.free_flight(sampler, queries, ray, si, medium, needs_intersection,
                                                           active_medium, channel, "shadow", remaining)
            is_spectral = medium.has_spectral_extinction() & active_medium
            not_spectral = ~is_spectral & active_medium
            dist = dr.minimum(remaining, dr.minimum(mei.t, si.t)) - mei.mint
            tr_ = dr.exp(-dist * mei.combined_extinction)
            free_flight_pdf = dr.select((si.t < mei.t) | (mei.t > remaining), tr_, tr_ * mei.combined_extinction)
            w = weigh.free_flight(w, tr_, free_flight_pdf, channel, is_spectral)
            # Sampled past the emitter: the shadow ray is done.
            total_dist = dr.select(active_medium & (mei.t > remaining) & mei.is_valid(), ds.dist, total_dist)
            mei.t = dr.select(active_medium & (mei.t > remaining), dr.inf, mei.t)
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            is_spectral &= active_medium
            not_spectral &= active_medium
            total_dist = dr.select(active_medium, total_dist + mei.t, total_dist)
            ray.o = dr.select(active_medium, mei.p, ray.o)
            si.t = dr.select(active_medium, si.t - mei.t, si.t)
            w = weigh.null_collision(w, mei, channel, is_spectral, not_spectral)

        intersect = active_surface & needs_intersection
        si = dr.select(intersect, self.hit(queries, ray, intersect, "shadow"), si)
        needs_intersection &= ~intersect
        active_surface |= escaped_medium
        total_dist = dr.select(active_surface, total_dist + si.t, total_dist)
        active_surface &= si.is_valid() & active & ~active_medium
        w = weigh.null_surface(w, si.bsdf(ray).eval_null_transmission(si, active_surface), si, channel, active_surface)
        ray = dr.select(active_surface, queries.spawn(si, ray.d), ray)
        ray.maxt = remaining
        needs_intersection |= active_surface
        active &= (active_medium | active_surface) & weigh.passes(w)
        if use.media.on:
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
        return ShadowState(active=active, ray=ray, total_dist=total_dist, needs_intersection=needs_intersection,
                           medium=medium, si=si, weights=w)

    def describe(self) -> str:
        return f"max_depth={self.max_depth}, rr_depth={self.rr_depth}"
