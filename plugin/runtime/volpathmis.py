"""The `layerbvh_volpathmis` integrator: Mitsuba's `volpathmis` (volumetric path tracing with spectral MIS over path-space weights) with every ray query answered by the Layer BVH traversal."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.volpath import LayerBVHVolPath, index_spectrum


# -- path weights: p/f ratios, one row per colour channel (spectral MIS) or one spectrum --------------
class PathWeights:
    """Stock volpathmis's `WeightMatrix` and its operations. With spectral MIS (the default) a
    path's weights are an n x n matrix: row i holds, for every channel j, the path's pdf had
    channel j been sampled over its contribution in channel i; the MIS weight of channel i is
    n / sum_j row_i[j] (the balance heuristic over the channels that could have sampled the path).
    Without it, one spectrum of p/f with the pdf of the channel that was sampled. A matrix is a
    list of n rows (mi.UnpolarizedSpectrum): Dr.Jit has no 1x1 matrix for the mono variants."""

    def __init__(self, spectral_mis: bool):
        self.spectral_mis = spectral_mis
        self.n = dr.size_v(mi.UnpolarizedSpectrum)

    def ones(self, width: int):
        one = dr.full(mi.UnpolarizedSpectrum, 1, width)
        return [mi.UnpolarizedSpectrum(one) for _ in range(self.n)] if self.spectral_mis else one

    def copy(self, w):
        return [mi.UnpolarizedSpectrum(r) for r in w] if self.spectral_mis else mi.UnpolarizedSpectrum(w)

    def select(self, mask, a, b):
        if self.spectral_mis:
            return [mi.UnpolarizedSpectrum(dr.select(mask, x, y)) for x, y in zip(a, b)]
        return mi.UnpolarizedSpectrum(dr.select(mask, a, b))

    def update(self, w, p, f, channel, active):
        """Stock's `update_weights`: multiply the ratios p/f in (where `active`); a ratio that is not
        finite (f = 0: the path cannot carry light in that channel) becomes 0."""
        p, f = mi.UnpolarizedSpectrum(p), mi.UnpolarizedSpectrum(f)
        if self.spectral_mis:
            out = []
            for i in range(self.n):
                ratio = p / f[i]
                ratio = dr.select(dr.isfinite(ratio), ratio, 0) * w[i]
                out.append(mi.UnpolarizedSpectrum(dr.select(active, dr.select(dr.isnan(ratio), 0, ratio), w[i])))
            return out  # (the type kept: spectral variants' arithmetic returns plain arrays, loops refuse the change)
        ratio = w * (index_spectrum(p, channel) / f)
        return mi.UnpolarizedSpectrum(dr.select(active, dr.select(dr.isfinite(ratio), ratio, 0), w))

    def weight(self, w) -> mi.UnpolarizedSpectrum:
        """The path's MIS-weighted throughput (stock's `mis_weight(p_over_f)`): per channel n over
        its row's sum (spectral MIS), else 1 / (p/f); 0 where that is undefined."""
        if self.spectral_mis:
            out = dr.zeros(mi.UnpolarizedSpectrum, dr.width(w[0]))
            for i, row in enumerate(w):
                total = dr.sum(row, axis=0)
                out[i] = dr.select(total == 0, 0, self.n / total)
            return out
        return dr.select(dr.min(dr.abs(w), axis=0) == 0, 0, 1 / w)

    def weight2(self, a, b) -> mi.UnpolarizedSpectrum:
        """The MIS-weighted throughput of one path found by two techniques (stock's `mis_weight(p1, p2)`):
        the weight of the two sets of ratios summed."""
        return self.weight([x + y for x, y in zip(a, b)] if self.spectral_mis else a + b)

    def any_nonzero(self, w, nee):
        """Stock's shadow-loop condition: light can still pass (spectral MIS: the weight of the
        unidirectional path; otherwise either set of ratios)."""
        if self.spectral_mis:
            return dr.any(self.weight(w) != 0)
        return dr.any(w != 0) | dr.any(nee != 0)


@dataclass
class VolPathMISState:
    """What a path carries from one loop iteration to the next (stock volpathmis's LoopState)."""

    active: mi.Bool
    depth: mi.UInt32
    ray: mi.Ray3f
    p_over_f: object                       # PathWeights of the path sampled so far (rows, or a spectrum)
    p_over_f_nee: object                   # the same path's, had its last vertex been found by emitter sampling
    result: mi.Spectrum
    si: mi.SurfaceInteraction3f
    mei: mi.MediumInteraction3f
    medium: mi.MediumPtr
    eta: mi.Float
    last_scatter_event: mi.Interaction3f
    last_event_was_null: mi.Bool           # no Russian roulette right after a null collision
    needs_intersection: mi.Bool
    specular_chain: mi.Bool
    valid_ray: mi.Bool


class ShadowWeights:
    """volpathmis's shadow-ray weights: the pair (p_over_f_nee, p_over_f_uni) of PathWeights, as
    stock updates them at each free flight, null collision and null surface (the operations of
    volpath.Transmittance)."""

    def __init__(self, weights: PathWeights):
        self.W = weights

    def free_flight(self, w, tr, free_flight_pdf, channel, is_spectral):
        nee, uni = w
        return (self.W.update(nee, free_flight_pdf, tr, channel, is_spectral),
                self.W.update(uni, free_flight_pdf, tr, channel, is_spectral))

    def null_collision(self, w, mei, channel, is_spectral, not_spectral):
        W, (nee, uni) = self.W, w
        nee = W.update(nee, 1, mei.sigma_n, channel, is_spectral)
        uni = W.update(uni, dr.mean(mei.sigma_n / mei.combined_extinction, axis=0), mei.sigma_n, channel, is_spectral)
        nee = W.update(nee, 1, mei.sigma_n / mei.combined_extinction, channel, not_spectral)
        uni = W.update(uni, mei.sigma_n, mei.sigma_n, channel, not_spectral)
        return nee, uni

    def null_surface(self, w, bsdf_val, si, channel, active):
        nee, uni = w
        return self.W.update(nee, 1, bsdf_val, channel, active), self.W.update(uni, 1, bsdf_val, channel, active)

    def passes(self, w):
        nee, uni = w
        return self.W.any_nonzero(uni, nee)


class LayerBVHVolPathMIS(LayerBVHVolPath):
    r"""Volumetric path tracer with spectral MIS (the same estimator as stock ``volpathmis``)
    tracing with layerbvh.

    Algorithm (stock ``volpathmis``'s ``sample``): ``volpath``'s random walk, in the same order of
    sampler calls (``LayerBVHVolPath``), with path weights kept as ratios p/f rather than a
    throughput (``PathWeights``): every sampling decision whose pdf differs between colour
    channels (free flights in a medium with spectrally varying extinction, null versus real
    collisions) enters each channel's pdf, and light is weighted by the balance heuristic over
    the channels (Miller et al. 2019, "A null-scattering path integral formulation of light
    transport"), which removes the colour noise of volpath's single-channel sampling in chromatic
    media. Emitter sampling and BSDF/phase sampling are combined the same way (a second set of
    ratios, ``p_over_f_nee``, for the path as emitter sampling would have found it); shadow rays
    carry both sets through null surfaces and media (ratio tracking, ``next_1d`` per step).
    Russian roulette is skipped right after a null collision; a BSDF sample of pdf 0 ends its
    path there.

    Properties: ``max_depth`` (-1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false),
    ``use_spectral_mis`` (true) as in ``volpathmis``; ``traversal`` and the rest as in
    ``layerbvh``. Polarized variants are refused (as stock)."""

    STATE = VolPathMISState

    def __init__(self, props: mi.Properties):
        if mi.is_polarized:
            raise ValueError(f"layerbvh_volpathmis: volpathmis does not support polarized variants (as stock); the "
                             f"active variant is {mi.variant()}")
        self.use_spectral_mis = props.get("use_spectral_mis", True)
        LayerBVHVolPath.__init__(self, props)
        self.weights = PathWeights(self.use_spectral_mis)

    def _start_weights(self, n: int) -> dict:
        return {"p_over_f": self.weights.ones(n), "p_over_f_nee": self.weights.ones(n),
                "last_event_was_null": dr.full(mi.Bool, False, n)}

    # -- one loop iteration ---------------------------------------------------------------------
    def _iteration(self, scene, sampler, use, queries, s: VolPathMISState, channel, megakernel: bool, hint: str):
        W = self.weights
        active, depth, ray, result = s.active, s.depth, mi.Ray3f(s.ray), s.result
        p_over_f, p_over_f_nee = W.copy(s.p_over_f), W.copy(s.p_over_f_nee)
        si, mei, medium, eta, last_event = s.si, s.mei, s.medium, s.eta, s.last_scatter_event
        needs_intersection, specular_chain, valid_ray = s.needs_intersection, s.specular_chain, s.valid_ray
        cap = self._depth_cap

        # -- Russian roulette (not right after a null collision), then the depth limit
        q = dr.minimum(dr.max(W.weight(p_over_f), axis=0) * dr.square(eta), 0.95)
        perform_rr = active & ~s.last_event_was_null & (depth > self.rr_depth)
        active &= ~((sampler.next_1d(active) >= q) & perform_rr)
        p_over_f = W.update(p_over_f, dr.detach(q), 1, channel, perform_rr)
        last_event_was_null = dr.full(mi.Bool, False, dr.width(active))
        active &= depth < cap
        active &= dr.any(W.weight(p_over_f) != 0)

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
            p_over_f = W.update(p_over_f, free_flight_pdf, tr, channel, is_spectral)
            p_over_f_nee = W.update(p_over_f_nee, free_flight_pdf, tr, channel, is_spectral)
            escaped_medium = active_medium & ~mei.is_valid()
            active_medium &= mei.is_valid()
            is_spectral &= active_medium
            not_spectral &= active_medium

            null_scatter_prob = dr.mean(mei.sigma_n / mei.combined_extinction, axis=0)
            null_scatter = sampler.next_1d(active_medium) < null_scatter_prob
            act_null_scatter = null_scatter & active_medium
            act_medium_scatter = ~act_null_scatter & active_medium
            last_event_was_null = act_null_scatter
            depth = dr.select(act_medium_scatter, depth + 1, depth)
            last_event = dr.select(act_medium_scatter, mi.Interaction3f(mei), last_event)
            sample_emitters = mei.medium.use_emitter_sampling()
            active &= depth < cap
            act_medium_scatter &= active
            specular_chain &= ~act_medium_scatter
            specular_chain |= act_medium_scatter & ~sample_emitters

            # A null collision moves the ray on; the surface ahead stays the same.
            spectral_null, plain_null = is_spectral & act_null_scatter, not_spectral & act_null_scatter
            p_over_f = W.update(p_over_f, null_scatter_prob, mei.sigma_n, channel, spectral_null)
            p_over_f_nee = W.update(p_over_f_nee, 1, mei.sigma_n, channel, spectral_null)
            p_over_f = W.update(p_over_f, mei.sigma_n, mei.sigma_n, channel, plain_null)
            p_over_f_nee = W.update(p_over_f_nee, 1, null_scatter_prob, channel, plain_null)
            ray.o = dr.select(act_null_scatter, mei.p, ray.o)
            si.t = dr.select(act_null_scatter, si.t - mei.t, si.t)

            # A real collision scatters: emitter sampling, then phase function sampling.
            p_over_f = W.update(p_over_f, 1 - null_scatter_prob, mei.sigma_s, channel, is_spectral & act_medium_scatter)
            p_over_f = W.update(p_over_f, mei.sigma_t, mei.sigma_s, channel, not_spectral & act_medium_scatter)
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            valid_ray |= act_medium_scatter
            active_e = act_medium_scatter & sample_emitters
            if use.emitter_sampling.on:
                nee_end, uni_end, emitted, ds = self._sample_emitter_mis(mei, False, scene, sampler, use, queries,
                                                                         medium, p_over_f, channel, active_e,
                                                                         megakernel)
                phase_val, phase_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, active_e)
                nee_end = W.update(nee_end, 1, phase_val, channel, active_e)
                uni_end = W.update(uni_end, dr.select(ds.delta, 0, phase_pdf), phase_val, channel, active_e)
                result = dr.select(active_e, result + W.weight2(nee_end, uni_end) * emitted, result)
            else:
                sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same
            p_over_f_nee = W.select(act_medium_scatter, p_over_f, p_over_f_nee)

            phase = dr.select(act_medium_scatter, phase, dr.zeros(mi.PhaseFunctionPtr))
            sample_2 = sampler.next_2d(act_medium_scatter)  # (stock: right to left)
            sample_1 = sampler.next_1d(act_medium_scatter)
            wo, phase_weight, phase_pdf = phase.sample(phase_ctx, mei, sample_1, sample_2, act_medium_scatter)
            ray = dr.select(act_medium_scatter, mei.spawn_ray(wo), ray)
            needs_intersection |= act_medium_scatter
            p_over_f = W.update(p_over_f, phase_pdf, phase_weight * phase_pdf, channel, act_medium_scatter)
            p_over_f_nee = W.update(p_over_f_nee, 1, phase_weight * phase_pdf, channel, act_medium_scatter)

        # -- surfaces: the hit, emission found there, emitter sampling, BSDF sampling
        active_surface |= escaped_medium
        intersect = active_surface & needs_intersection
        si = self._surface_hit(queries, ray, si, intersect, depth, hint, megakernel)

        if use.emitter_hits.on:
            active_e, count_direct, emitter_pdf, emitted = self._emitter_hit(scene, si, active_surface, depth,
                                                                             specular_chain, last_event)
            p_over_f_nee = W.update(p_over_f_nee, emitter_pdf, 1, channel, active_e)
            contrib = dr.select(count_direct, W.weight(p_over_f) * emitted, W.weight2(p_over_f, p_over_f_nee) * emitted)
            result = dr.select(active_e, result + contrib, result)

        active_surface &= si.is_valid()
        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        active_e = active_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth + 1 < cap)
        if use.emitter_sampling.on:
            nee_end, uni_end, emitted, ds = self._sample_emitter_mis(si, True, scene, sampler, use, queries, medium,
                                                                     p_over_f, channel, active_e, megakernel)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_e)
            nee_end = W.update(nee_end, 1, bsdf_val, channel, active_e)
            uni_end = W.update(uni_end, dr.select(ds.delta, 0, bsdf_pdf), bsdf_val, channel, active_e)
            result = dr.select(active_e, result + W.weight2(nee_end, uni_end) * emitted, result)
        else:
            sampler.next_2d(active_e)  # stock's emitter sample, drawn all the same

        sample_2 = sampler.next_2d(active_surface)  # (stock: right to left)
        sample_1 = sampler.next_1d(active_surface)
        bs, bsdf_weight = bsdf.sample(ctx, si, sample_1, sample_2, active_surface)
        invalid_bsdf_sample = active_surface & (bs.pdf == 0)
        active_surface &= bs.pdf > 0
        eta = dr.select(active_surface, eta * bs.eta, eta)
        ray = dr.select(active_surface, si.spawn_ray(si.to_world(bs.wo)), ray)
        needs_intersection |= active_surface

        non_null = active_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        valid_ray |= non_null | invalid_bsdf_sample
        specular_chain |= non_null & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        specular_chain &= ~(active_surface & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
        depth = dr.select(non_null, depth + 1, depth)
        last_event = dr.select(non_null, mi.Interaction3f(si), last_event)
        p_over_f_nee = W.select(non_null, p_over_f, p_over_f_nee)
        p_over_f = W.update(p_over_f, bs.pdf, bsdf_weight * bs.pdf, channel, active_surface)
        p_over_f_nee = W.update(p_over_f_nee, 1, bsdf_weight * bs.pdf, channel, non_null)
        if use.media.on:
            medium = dr.select(active_surface & si.is_medium_transition(), si.target_medium(ray.d), medium)
        active &= active_surface | active_medium
        return sampler, VolPathMISState(
            active=active, depth=depth, ray=ray, p_over_f=p_over_f, p_over_f_nee=p_over_f_nee, result=result, si=si,
            mei=mei, medium=medium, eta=eta, last_scatter_event=last_event, last_event_was_null=last_event_was_null,
            needs_intersection=needs_intersection, specular_chain=specular_chain, valid_ray=valid_ray)

    # -- emitter sampling with both sets of weights along the shadow ray -----------------------------
    def _sample_emitter_mis(self, ref, on_surface: bool, scene, sampler, use, queries, medium, p_over_f, channel,
                            active, megakernel: bool):
        """Stock volpathmis's `sample_emitter`: an emitter sample from `ref` and the path's two sets
        of weights through to it (as found by emitter sampling, and as a unidirectional path
        would be), with the emitter's value (not divided by its pdf: the weights hold the pdfs)."""
        W = self.weights
        ds, emitter_weight = scene.sample_emitter_direction(ref, sampler.next_2d(active), False, active)
        emitter_val = dr.select(ds.pdf == 0, 0, emitter_weight * ds.pdf)
        active = active & (ds.pdf != 0)
        nee = W.update(W.copy(p_over_f), ds.pdf, 1, channel, active)
        uni = W.copy(p_over_f)
        ray = ref.spawn_ray_to(ds.p)
        if not use.transmittance.on:
            # No medium and no null surface: light is blocked by the first hit (stock's loop then
            # ends at its first surface, whose null transmission sets every ratio to 0).
            return nee, uni, dr.select(active & queries.occluded(ray, active), 0, emitter_val), ds

        if on_surface and use.media.on:
            medium = dr.select(ref.is_medium_transition(), ref.target_medium(ray.d), medium)
        nee, uni = self._shadow_walk(sampler, use, queries, ray, medium, channel, ds, active, (nee, uni),
                                     ShadowWeights(W), megakernel)
        return nee, uni, emitter_val, ds

    def to_string(self):
        return (f"LayerBVHVolPathMISIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"use_spectral_mis={self.use_spectral_mis}, traversal={self.traversal}, branching={self.branching}, "
                f"treelet_height={self.treelet_height}]")

