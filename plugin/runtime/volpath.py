"""The `layerbvh_volpath` integrator: Mitsuba's `volpath` (volumetric path tracing with participating media) with every ray query answered by the Layer BVH traversal."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.held_instances import instances_held
from layerbvh_mitsuba.runtime.integrator import LayerBVHPathTracer, SceneState, loop, mis_weight

UINT32_MAX = 2 ** 32 - 1  # stock keeps max_depth as uint32: -1 (infinite) is this


def index_spectrum(spec, channel):
    """The component `channel` of an unpolarized spectrum in RGB variants (the channel that
    drives free-flight sampling); the first component otherwise, as stock."""
    m = spec[0]
    if mi.is_rgb:
        m = dr.select(channel == 1, spec[1], m)
        m = dr.select(channel == 2, spec[2], m)
    return m


def _unpolarized(x):
    return mi.unpolarized_spectrum(x)


@dataclass
class VolPathState:
    """What a path carries from one loop iteration to the next (stock volpath's LoopState)."""

    active: mi.Bool
    depth: mi.UInt32
    ray: mi.Ray3f
    throughput: mi.Spectrum
    result: mi.Spectrum
    si: mi.SurfaceInteraction3f            # the surface the ray reaches (kept across null scattering)
    mei: mi.MediumInteraction3f
    medium: mi.MediumPtr                   # the medium the ray travels in (null: none)
    eta: mi.Float
    last_scatter_event: mi.Interaction3f   # for the MIS weight of emission found by a sampled direction
    last_scatter_direction_pdf: mi.Float
    needs_intersection: mi.Bool            # `si` is stale: the ray changed since it was found
    specular_chain: mi.Bool                # only delta events (or scattering without emitter sampling) so far
    valid_ray: mi.Bool


@dataclass
class ShadowState:
    """The transmittance loop's state (stock volpath's and volpathmis's `sample_emitter` LoopState)."""

    active: mi.Bool
    ray: mi.Ray3f
    total_dist: mi.Float
    needs_intersection: mi.Bool
    medium: mi.MediumPtr
    si: mi.SurfaceInteraction3f
    weights: object  # what the light carries along the way: `Transmittance` (volpath) or volpathmis's weights


class Transmittance:
    """volpath's shadow-ray weights: the transmittance, a spectrum, as stock's ratio tracking
    updates it at each free flight, null collision and null surface (volpathmis keeps p/f ratios
    instead: volpathmis.ShadowWeights, the same four operations)."""

    @staticmethod
    def free_flight(w, tr, free_flight_pdf, channel, is_spectral):
        tr_pdf = index_spectrum(free_flight_pdf, channel)
        return dr.select(is_spectral, w * dr.select(tr_pdf > 0, tr / tr_pdf, 0), w)

    @staticmethod
    def null_collision(w, mei, channel, is_spectral, not_spectral):
        w = dr.select(is_spectral, w * mei.sigma_n, w)
        return dr.select(not_spectral, w * mei.sigma_n / mei.combined_extinction, w)

    @staticmethod
    def null_surface(w, bsdf_val, si, channel, active):
        return dr.select(active, w * si.to_world_mueller(bsdf_val, si.wi, si.wi), w)

    @staticmethod
    def passes(w):
        return dr.any(_unpolarized(w) != 0)


class LayerBVHVolPath(LayerBVHPathTracer):
    r"""Volumetric path tracer (the same estimator as stock ``volpath``) tracing with layerbvh.

    Algorithm (stock ``volpath``'s ``sample``), per loop iteration: Russian roulette on the
    throughput (``next_1d``); in a medium, sample a free flight (``next_1d``) along the ray, find
    the surface the ray reaches (our closest-hit traversal, up to the sampled distance in a
    homogeneous medium) and choose null or real scattering (``next_1d``); at a real scattering
    event sample an emitter (``next_2d``) and estimate the transmittance towards it, then sample
    the phase function (``next_2d``, ``next_1d``); at a surface add the emission found there
    (MIS-weighted against emitter sampling), sample an emitter with transmittance (BSDFs with a
    smooth lobe), sample the BSDF (``next_2d``, ``next_1d``) and switch media where the surface
    is a medium transition. In RGB variants a colour channel that drives free-flight sampling is
    drawn first (``next_1d``). Transmittance towards an emitter is estimated by stepping along
    the shadow ray with closest-hit queries: through null surfaces (their null transmission) and
    media boundaries, with ratio tracking in each medium (``next_1d`` per step). Sampler use is
    in exactly this order and with stock's masks (stock's build evaluates a call's arguments
    right to left: the 2D sample before the 1D one), so a same-seed render matches stock
    ``volpath`` up to floating-point noise.

    Loop modes as in ``layerbvh``: the megakernel (``per_ray``, ``embree``: one kernel, the
    transmittance loop nested in the bounce loop) or between kernels (a Python loop per level).

    The feature plan leaves out what the scene does not need: free-flight sampling when it holds
    no medium, and the closest-hit transmittance steps when it has neither a medium nor a
    null-BSDF surface (a shadow ray is then blocked by its first hit: our any-hit traversal).
    Samples masked off on every lane change no independent sampler's stream and are not drawn;
    every other sample is drawn as stock draws it.

    Properties: ``max_depth`` (-1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false) as in
    ``volpath``; ``traversal``, ``branching``, ``treelet_height``, ``leaf_size``, ``stats``,
    ``adaptive`` and ``batch_rays`` as in ``layerbvh``.
    """

    VOLUMETRIC = True
    STATE = VolPathState  # the loop's state (volpathmis: its own)

    def __init__(self, props: mi.Properties):
        LayerBVHPathTracer.__init__(self, props)
        self._depth_cap = UINT32_MAX if self.max_depth < 0 else self.max_depth

    # -- auto: the kinds of batch this integrator traces ---------------------------------------
    def _auto_kinds(self, state: SceneState) -> list[tuple[bool, str]]:
        if self.max_depth == 0:
            return []
        kinds = [(False, "camera")]
        if self.max_depth < 0 or self.max_depth > 1:
            kinds.append((False, "bounce"))
        if state.features.emitter_sampling.on:
            kinds.append((not state.features.transmittance.on, "shadow"))
        return kinds

    def _auto_rule(self, state: SceneState) -> str | None:
        """Media or null surfaces: the megakernel. Between kernels every null collision and
        every transmittance step is a loop iteration with a host round trip; measured (scripts/
        bench_volpath_loops.py, 48x48, 16 spp) the wavefront loop 7.7x slower than per_ray on
        test_homo_emitter_inside_medium and 126x on test_hetero_sigmat, more than sorting could
        win back on its batches."""
        if state.features.media.on or state.features.transmittance.on:
            return ("volpath with media or null surfaces: per_ray in one megakernel (between kernels, "
                    "every null collision and transmittance step costs a host round trip: measured 8-126x "
                    "slower on Mitsuba's media scenes)")
        return None

    def _prepass_paths(self, scene, state: SceneState, cam: mi.Ray3f, sampler) -> None:
        """The pre-pass's work: the first two loop iterations of these camera rays."""
        s, channel = self._start(scene, sampler, cam, None, dr.full(mi.Bool, True, dr.width(cam.o)))
        for i in range(2):
            sampler, s = self._iteration(scene, sampler, state.features, state.tracer, s, channel, False,
                                         "camera" if i == 0 else "bounce")

    # -- one camera ray per sample ----------------------------------------------------------------
    @instances_held()
    def sample(self, scene, sampler, ray, medium=None, active=True):
        state = self.scene_state(scene)
        start = self._begin(scene, state, ray)
        megakernel = self.megakernel()
        queries = self._queries(scene, state.tracer, megakernel)
        n = dr.width(ray.o)
        s, channel = self._start(scene, sampler, mi.Ray3f(ray), medium, mi.Bool(active) & dr.full(mi.Bool, True, n))
        iteration = [0]

        def body(sampler, s):
            hint = "camera" if iteration[0] == 0 else "bounce"  # (between kernels: the first iteration's rays)
            iteration[0] += 1
            if not megakernel:
                self._vertices += 1
            return self._iteration(scene, sampler, state.features, queries, s, channel, megakernel, hint)

        sampler, s = loop((sampler, s), cond=lambda sampler, s: s.active, body=body, symbolic=megakernel,
                          label="layerbvh volpath")
        self._finish(state, start, megakernel)
        return s.result, s.valid_ray, []

    def _start(self, scene, sampler, ray: mi.Ray3f, medium, active) -> tuple[VolPathState, object]:
        """The loop's first state, and the colour channel that drives free-flight sampling (RGB:
        drawn first, `next_1d`)."""
        n = dr.width(active)
        channel = mi.UInt32(0)
        if mi.is_rgb:
            channels = dr.size_v(mi.Spectrum)
            channel = mi.UInt32(dr.minimum(sampler.next_1d(active) * channels, channels - 1))
        medium = dr.zeros(mi.MediumPtr, n) if medium is None else dr.full(mi.MediumPtr, medium, n)
        state = self.STATE(
            active=active, depth=dr.zeros(mi.UInt32, n), ray=ray, result=dr.zeros(mi.Spectrum, n),
            si=dr.zeros(mi.SurfaceInteraction3f, n), mei=dr.zeros(mi.MediumInteraction3f, n), medium=medium,
            eta=dr.full(mi.Float, 1, n), last_scatter_event=dr.zeros(mi.Interaction3f, n),
            needs_intersection=dr.full(mi.Bool, True, n), specular_chain=active & (not self.hide_emitters),
            valid_ray=dr.full(mi.Bool, (not self.hide_emitters) and scene.environment() is not None, n),
            **self._start_weights(n))
        return state, channel

    def _start_weights(self, n: int) -> dict:
        """The first state's fields that carry the path's weight (volpath: its throughput and the
        last scattering's direction pdf; volpathmis: its ratios)."""
        return {"throughput": dr.full(mi.Spectrum, 1, n), "last_scatter_direction_pdf": dr.full(mi.Float, 1, n)}

    @staticmethod
    def _hit(queries, ray: mi.Ray3f, active, hint: str) -> mi.SurfaceInteraction3f:
        """Stock's `scene.ray_intersect`: the closest hit (our traversal), fully interpolated."""
        return queries.intersect(ray, active, hint=hint).compute_surface_interaction(ray, mi.RayFlags.All, active)

    def _free_flight(self, sampler, queries, ray: mi.Ray3f, si, medium, needs_intersection, active_medium, channel,
                     hint: str, remaining=None):
        """A free flight in the ray's medium (`next_1d`) and the surface it reaches (our closest
        hit, up to the sampled distance in a homogeneous medium, `remaining` at most on a shadow
        ray): (the medium interaction, inf where the surface comes first; the surface; needs_intersection)."""
        mei = medium.sample_interaction(ray, sampler.next_1d(active_medium), channel, active_medium)
        maxt = mei.t if remaining is None else dr.minimum(mei.t, remaining)
        ray.maxt = dr.select(active_medium & medium.is_homogeneous() & mei.is_valid(), maxt, ray.maxt)
        intersect = needs_intersection & active_medium
        si = dr.select(intersect, self._hit(queries, ray, intersect, hint), si)
        needs_intersection &= ~active_medium
        mei.t = dr.select(active_medium & (si.t < mei.t), dr.inf, mei.t)
        return mei, si, needs_intersection

    def _emitter_hit(self, scene, si, active_surface, depth, specular_chain, last_event):
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

    def _surface_hit(self, queries, ray: mi.Ray3f, si, intersect, depth, hint: str, megakernel: bool):
        """The surface a ray reaches where `intersect` (kept from before elsewhere); with
        hide_emitters a camera ray that hits an area emitter continues behind it (as stock)."""
        si = dr.select(intersect, self._hit(queries, ray, intersect, hint), si)
        if self.hide_emitters:
            skip = si.is_valid() & (si.shape.emitter() != None) & (depth == 0) & intersect  # noqa: E711
            behind = si.spawn_ray(ray.d)
            pi = self._skip_area_emitters(queries, behind, queries.intersect(behind, skip, hint=hint), skip,
                                          megakernel)
            si = dr.select(skip, pi.compute_surface_interaction(behind, mi.RayFlags.All, skip), si)
        return si

    # -- one loop iteration ---------------------------------------------------------------------
    def _iteration(self, scene, sampler, use, queries, s: VolPathState, channel, megakernel: bool, hint: str):
        active, depth, ray, throughput, result = s.active, s.depth, mi.Ray3f(s.ray), s.throughput, s.result
        si, mei, medium, eta = s.si, s.mei, s.medium, s.eta
        last_event, last_pdf = s.last_scatter_event, s.last_scatter_direction_pdf
        needs_intersection, specular_chain, valid_ray = s.needs_intersection, s.specular_chain, s.valid_ray
        cap = self._depth_cap

        # -- Russian roulette (on the depth reached so far), then the depth limit
        active &= dr.any(_unpolarized(throughput) != 0)
        q = dr.minimum(dr.max(_unpolarized(throughput)) * dr.square(eta), 0.95)
        perform_rr = depth > self.rr_depth
        active &= (sampler.next_1d(active) < q) | ~perform_rr
        throughput = dr.select(perform_rr, throughput * dr.rcp(dr.detach(q)), throughput)
        active &= depth < cap

        # -- sampling the RTE in a medium: free flight, then null or real scattering
        active_medium = active & (medium != None)  # noqa: E711  (a Dr.Jit pointer array against null)
        active_surface = active & ~active_medium
        act_medium_scatter = mi.Bool(False)
        escaped_medium = mi.Bool(False)
        if use.media.on:
            is_spectral = active_medium & medium.has_spectral_extinction()
            not_spectral = ~is_spectral & active_medium
            mei, si, needs_intersection = self._free_flight(sampler, queries, ray, si, medium, needs_intersection,
                                                            active_medium, channel, hint)
            tr, free_flight_pdf = medium.transmittance_eval_pdf(mei, si, is_spectral)
            tr_pdf = index_spectrum(free_flight_pdf, channel)
            throughput = dr.select(is_spectral, throughput * dr.select(tr_pdf > 0, tr / tr_pdf, 0), throughput)
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()

            null_scatter_prob = dr.mean(mei.sigma_n / mei.combined_extinction, axis=0)
            null_scatter = sampler.next_1d(active_medium) < null_scatter_prob
            act_null_scatter = null_scatter & active_medium
            act_medium_scatter = ~act_null_scatter & active_medium
            throughput = dr.select(is_spectral & act_null_scatter, throughput * mei.sigma_n / null_scatter_prob,
                                   throughput)
            depth = dr.select(act_medium_scatter, depth + 1, depth)
            last_event = dr.select(act_medium_scatter, mi.Interaction3f(mei), last_event)

            # No lighting is estimated beyond the depth limit.
            active &= depth < cap
            act_medium_scatter &= active

            # A null collision moves the ray on; the surface ahead stays the same.
            ray.o = dr.select(act_null_scatter, mei.p, ray.o)
            si.t = dr.select(act_null_scatter, si.t - mei.t, si.t)

            # A real collision scatters: emitter sampling, then phase function sampling.
            throughput = dr.select(is_spectral & act_medium_scatter,
                                   throughput * mei.sigma_s / dr.mean(mei.sigma_t / mei.combined_extinction, axis=0),
                                   throughput)
            throughput = dr.select(not_spectral & act_medium_scatter, throughput * mei.sigma_s / mei.sigma_t,
                                   throughput)
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            sample_emitters = mei.medium.use_emitter_sampling()
            valid_ray |= act_medium_scatter
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters
            active_e = act_medium_scatter & sample_emitters
            if use.emitter_sampling.on:
                emitted, ds = self._sample_emitter(mei, False, scene, sampler, use, queries, medium, channel,
                                                   active_e, megakernel)
                phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active_e)
                result = dr.select(active_e, result + throughput * phase_val * emitted
                                   * mis_weight(ds.pdf, dr.select(ds.delta, 0, phase_pdf)), result)
            else:
                sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same
            phase = dr.select(act_medium_scatter, phase, dr.zeros(mi.PhaseFunctionPtr))
            sample_2 = sampler.next_2d(act_medium_scatter)  # (stock: right to left, see the class docstring)
            sample_1 = sampler.next_1d(act_medium_scatter)
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sample_1, sample_2, act_medium_scatter)
            act_medium_scatter &= phase_pdf > 0
            ray = dr.select(act_medium_scatter, mei.spawn_ray(wo), ray)
            needs_intersection |= act_medium_scatter
            last_pdf = dr.select(act_medium_scatter, phase_pdf, last_pdf)
            throughput = dr.select(act_medium_scatter, throughput * phase_weight, throughput)

        # -- surfaces: the hit, emission found there, emitter sampling, BSDF sampling
        active_surface |= escaped_medium
        intersect = active_surface & needs_intersection
        si = self._surface_hit(queries, ray, si, intersect, depth, hint, megakernel)

        if use.emitter_hits.on:
            active_e, count_direct, emitter_pdf, emitted = self._emitter_hit(scene, si, active_surface, depth,
                                                                             specular_chain, last_event)
            contrib = dr.select(count_direct, throughput * emitted,
                                throughput * mis_weight(last_pdf, emitter_pdf) * emitted)
            result = dr.select(active_e, result + contrib, result)

        active_surface &= si.is_valid()
        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        active_e = active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < cap)
        if use.emitter_sampling.on:
            emitted, ds = self._sample_emitter(si, True, scene, sampler, use, queries, medium, channel, active_e,
                                               megakernel)
            wo = si.to_local(ds.d)
            bsdf_val = si.to_world_mueller(bsdf.eval(ctx, si, wo, active_e), -wo, si.wi)
            bsdf_pdf = bsdf.pdf(ctx, si, wo, active_e)
            result = dr.select(active_e, result + throughput * bsdf_val
                               * mis_weight(ds.pdf, dr.select(ds.delta, 0, bsdf_pdf)) * emitted, result)
        else:
            sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same: the sequence stays stock's

        sample_2 = sampler.next_2d(active_surface)  # (stock: right to left)
        sample_1 = sampler.next_1d(active_surface)
        bs, bsdf_val = bsdf.sample(ctx, si, sample_1, sample_2, active_surface)
        bsdf_val = si.to_world_mueller(bsdf_val, -bs.wo, si.wi)
        throughput = dr.select(active_surface, throughput * bsdf_val, throughput)
        eta = dr.select(active_surface, eta * bs.eta, eta)
        ray = dr.select(active_surface, si.spawn_ray(si.to_world(bs.wo)), ray)
        needs_intersection |= active_surface

        non_null = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        depth = dr.select(non_null, depth + 1, depth)
        last_event = dr.select(non_null, mi.Interaction3f(si), last_event)
        last_pdf = dr.select(non_null, bs.pdf, last_pdf)
        valid_ray |= non_null
        specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
        if use.media.on:
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
        active &= active_surface | active_medium
        return sampler, VolPathState(
            active=active, depth=depth, ray=ray, throughput=throughput, result=result, si=si, mei=mei, medium=medium,
            eta=eta, last_scatter_event=last_event, last_scatter_direction_pdf=last_pdf,
            needs_intersection=needs_intersection, specular_chain=specular_chain, valid_ray=valid_ray)

    # -- emitter sampling with transmittance ----------------------------------------------------------
    def _sample_emitter(self, ref, on_surface: bool, scene, sampler, use, queries, medium, channel, active,
                        megakernel: bool):
        """Stock volpath's `sample_emitter`: an emitter sample from `ref` (a surface or medium
        interaction) and its emission times the transmittance along the shadow ray."""
        ds, emitter_val = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        emitter_val = dr.select(ds.pdf == 0, 0, emitter_val)
        active = active & (ds.pdf != 0)
        ray = ref.spawn_ray_to(ds.p)
        if not use.transmittance.on:
            # No medium and no null surface: light is blocked by the first hit (stock's loop then
            # ends at its first surface, whose null transmission is zero).
            return dr.select(active & queries.occluded(ray, active), 0, emitter_val), ds

        if on_surface and use.media.on:
            medium = dr.select(ref.is_medium_transition(), ref.target_medium(ray.d), medium)
        transmittance = self._shadow_walk(sampler, use, queries, ray, medium, channel, ds, active,
                                          dr.full(mi.Spectrum, 1, dr.width(active)), Transmittance, megakernel)
        return transmittance * emitter_val, ds

    def _shadow_walk(self, sampler, use, queries, ray: mi.Ray3f, medium, channel, ds, active, weights, weigh,
                     megakernel: bool):
        """The shadow ray's loop (stock's in `sample_emitter`): step towards the emitter sample
        `ds` until it is reached or no light passes, carrying `weights` as `weigh` updates them
        (Transmittance, or volpathmis's ShadowWeights); the weights at the end."""
        max_dist = mi.Float(ray.maxt)
        n = dr.width(active)
        state = ShadowState(active=active, ray=ray, total_dist=dr.zeros(mi.Float, n),
                            needs_intersection=dr.full(mi.Bool, True, n), medium=medium,
                            si=dr.zeros(mi.SurfaceInteraction3f, n), weights=weights)

        def step(sampler, t: ShadowState):
            return sampler, self._transmittance_step(sampler, use, queries, t, channel, max_dist, ds, weigh)

        sampler, state = loop((sampler, state), cond=lambda sampler, t: t.active, body=step, symbolic=megakernel,
                              label="layerbvh volpath transmittance")
        return state.weights

    def _transmittance_step(self, sampler, use, queries, t: ShadowState, channel, max_dist, ds, weigh) -> ShadowState:
        """One step along a shadow ray: ratio tracking to the next collision in a medium, or the
        next surface, whose null transmission it crosses (a medium boundary switches media)."""
        active, ray, total_dist = t.active, mi.Ray3f(t.ray), t.total_dist
        needs_intersection, medium, si, w = t.needs_intersection, t.medium, t.si, t.weights
        remaining = max_dist - total_dist
        ray.maxt = remaining
        active &= remaining > 0
        active_medium = active & (medium != None)  # noqa: E711
        active_surface = active & ~active_medium
        escaped_medium = mi.Bool(False)
        if use.media.on:
            mei, si, needs_intersection = self._free_flight(sampler, queries, ray, si, medium, needs_intersection,
                                                            active_medium, channel, "shadow", remaining)
            is_spectral = medium.has_spectral_extinction() & active_medium
            not_spectral = ~is_spectral & active_medium
            dist = dr.minimum(remaining, dr.minimum(mei.t, si.t)) - mei.mint
            tr = dr.exp(-dist * mei.combined_extinction)
            free_flight_pdf = dr.select((si.t < mei.t) | (mei.t > remaining), tr, tr * mei.combined_extinction)
            w = weigh.free_flight(w, tr, free_flight_pdf, channel, is_spectral)
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
        si = dr.select(intersect, self._hit(queries, ray, intersect, "shadow"), si)
        needs_intersection &= ~intersect
        active_surface |= escaped_medium
        total_dist = dr.select(active_surface, total_dist + si.t, total_dist)
        active_surface &= si.is_valid() & active & ~active_medium
        w = weigh.null_surface(w, si.bsdf(ray).eval_null_transmission(si, active_surface), si, channel, active_surface)
        ray = dr.select(active_surface, si.spawn_ray(ray.d), ray)
        ray.maxt = remaining
        needs_intersection |= active_surface
        active &= (active_medium | active_surface) & weigh.passes(w)
        if use.media.on:
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
        return ShadowState(active=active, ray=ray, total_dist=total_dist, needs_intersection=needs_intersection,
                           medium=medium, si=si, weights=w)

    def to_string(self):
        return (f"LayerBVHVolPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"traversal={self.traversal}, branching={self.branching}, treelet_height={self.treelet_height}]")
