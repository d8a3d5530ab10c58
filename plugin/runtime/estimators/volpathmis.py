"""Stock `volpathmis`'s estimator (volumetric path tracing with spectral MIS over path-space weights): the shared
walk (media.MediaWalk) with a path weight kept as p/f ratios. Follows src/integrators/volpathmis.cpp @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.media import MediaWalk, index_spectrum


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
class Ratios:
    """volpathmis's path weight, in the walk's state (stock LoopState's fields)."""

    p_over_f: object             # PathWeights of the path sampled so far (rows, or a spectrum)
    p_over_f_nee: object         # the same path's, had its last vertex been found by emitter sampling
    last_event_was_null: mi.Bool  # no Russian roulette right after a null collision


class ShadowRatios:
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


class RatioWeights:
    """How each event of the walk changes volpathmis's `Ratios` (the strategy media.MediaWalk
    calls; volpath.ThroughputWeights is the other): every sampling decision enters each
    channel's pdf over the path's contribution."""

    def __init__(self, spectral_mis: bool):
        self.W = PathWeights(spectral_mis)
        self.shadow = ShadowRatios(self.W)

    def start(self, n: int) -> Ratios:
        return Ratios(self.W.ones(n), self.W.ones(n), dr.full(mi.Bool, False, n))

    def copy(self, w: Ratios) -> Ratios:
        return Ratios(self.W.copy(w.p_over_f), self.W.copy(w.p_over_f_nee), w.last_event_was_null)

    def roulette(self, sampler, w: Ratios, active, depth, eta, rr_depth: int, channel):
        """On the MIS-weighted throughput, past rr_depth and not right after a null collision
        (`next_1d`); a path of zero weight ends."""
        W = self.W
        q = dr.minimum(dr.max(W.weight(w.p_over_f), axis=0) * dr.square(eta), 0.95)
        perform_rr = active & ~w.last_event_was_null & (depth > rr_depth)
        active &= ~((sampler.next_1d(active) >= q) & perform_rr)
        p_over_f = W.update(w.p_over_f, dr.detach(q), 1, channel, perform_rr)
        active &= dr.any(W.weight(p_over_f) != 0)
        return active, Ratios(p_over_f, w.p_over_f_nee, dr.full(mi.Bool, False, dr.width(active)))

    def free_flight(self, w: Ratios, tr, free_flight_pdf, channel, is_spectral) -> Ratios:
        W = self.W
        return Ratios(W.update(w.p_over_f, free_flight_pdf, tr, channel, is_spectral),
                      W.update(w.p_over_f_nee, free_flight_pdf, tr, channel, is_spectral), w.last_event_was_null)

    def null_collision(self, w: Ratios, mei, null_scatter_prob, channel, spectral, plain, null) -> Ratios:
        W = self.W
        p_over_f = W.update(w.p_over_f, null_scatter_prob, mei.sigma_n, channel, spectral)
        p_over_f_nee = W.update(w.p_over_f_nee, 1, mei.sigma_n, channel, spectral)
        p_over_f = W.update(p_over_f, mei.sigma_n, mei.sigma_n, channel, plain)
        p_over_f_nee = W.update(p_over_f_nee, 1, null_scatter_prob, channel, plain)
        return Ratios(p_over_f, p_over_f_nee, null)

    def real_collision(self, w: Ratios, mei, null_scatter_prob, channel, spectral, plain) -> Ratios:
        W = self.W
        p_over_f = W.update(w.p_over_f, 1 - null_scatter_prob, mei.sigma_s, channel, spectral)
        p_over_f = W.update(p_over_f, mei.sigma_t, mei.sigma_s, channel, plain)
        return Ratios(p_over_f, w.p_over_f_nee, w.last_event_was_null)

    def scattered_in_medium(self, w: Ratios, scattered) -> Ratios:
        return Ratios(w.p_over_f, self.W.select(scattered, w.p_over_f, w.p_over_f_nee), w.last_event_was_null)

    def phase_sampled(self, w: Ratios, phase_weight, phase_pdf, channel, scattered):
        W, f = self.W, phase_weight * phase_pdf
        return scattered, Ratios(W.update(w.p_over_f, phase_pdf, f, channel, scattered),
                                 W.update(w.p_over_f_nee, 1, f, channel, scattered), w.last_event_was_null)

    def surface_emission(self, w: Ratios, emitted, emitter_pdf, count_direct, channel, active):
        W = self.W
        p_over_f_nee = W.update(w.p_over_f_nee, emitter_pdf, 1, channel, active)
        contrib = dr.select(count_direct, W.weight(w.p_over_f) * emitted, W.weight2(w.p_over_f, p_over_f_nee) * emitted)
        return contrib, Ratios(w.p_over_f, p_over_f_nee, w.last_event_was_null)

    @staticmethod
    def eval_bsdf(bsdf, ctx, si, ds, active):
        return bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active)

    def emitter_start(self, w: Ratios, ds, emitter_weight, channel, active):
        """(the emitter's value, not divided by its pdf: the ratios hold the pdfs; the path's two
        sets of ratios up to the emitter, as emitter sampling found it and as a unidirectional
        path would)."""
        W = self.W
        nee = W.update(W.copy(w.p_over_f), ds.pdf, 1, channel, active)
        return dr.select(ds.pdf == 0, 0, emitter_weight * ds.pdf), (nee, W.copy(w.p_over_f))

    @staticmethod
    def shadow_start(shadow_w, active):
        return shadow_w

    def direct(self, w: Ratios, shadow_w, emitter_val, f, pdf, ds, channel, active, on_surface: bool):
        """Emitter sampling's contribution: the two sets of ratios through f (phase or BSDF),
        MIS-weighted together, times the emitter's value."""
        W, (nee, uni) = self.W, shadow_w
        nee = W.update(nee, 1, f, channel, active)
        uni = W.update(uni, dr.select(ds.delta, 0, pdf), f, channel, active)
        return W.weight2(nee, uni) * emitter_val

    @staticmethod
    def bsdf_sampled(w: Ratios, bs, bsdf_weight, si, channel, active):
        """A BSDF sample of pdf 0 ends its path there (and still makes the sample valid)."""
        invalid = active & (bs.pdf == 0)
        return active & (bs.pdf > 0), invalid, w

    def surface_scattered(self, w: Ratios, bs, bsdf_weight, channel, active, non_null) -> Ratios:
        W, f = self.W, bsdf_weight * bs.pdf
        p_over_f_nee = W.select(non_null, w.p_over_f, w.p_over_f_nee)
        p_over_f = W.update(w.p_over_f, bs.pdf, f, channel, active)
        return Ratios(p_over_f, W.update(p_over_f_nee, 1, f, channel, non_null), w.last_event_was_null)


class VolPathMISEstimator(MediaWalk):
    r"""Volumetric path tracing with spectral MIS: the estimator of stock ``volpathmis``.

    Algorithm: ``volpath``'s random walk, in the same order of sampler calls (media.MediaWalk),
    with path weights kept as ratios p/f rather than a throughput (``RatioWeights``): every
    sampling decision whose pdf differs between colour channels (free flights in a medium with
    spectrally varying extinction, null versus real collisions) enters each channel's pdf, and
    light is weighted by the balance heuristic over the channels (Miller et al. 2019, "A
    null-scattering path integral formulation of light transport"), which removes the colour
    noise of volpath's single-channel sampling in chromatic media. Emitter sampling and
    BSDF/phase sampling are combined the same way (a second set of ratios, ``p_over_f_nee``, for
    the path as emitter sampling would have found it); shadow rays carry both sets through null
    surfaces and media (ratio tracking, ``next_1d`` per step). Russian roulette is skipped right
    after a null collision; a BSDF sample of pdf 0 ends its path there.

    Properties: ``max_depth`` (-1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false),
    ``use_spectral_mis`` (true) as in ``volpathmis``. Polarized variants are refused (as stock)."""

    PLUGIN = "volpathmis"

    def __init__(self, props: mi.Properties):
        if mi.is_polarized:
            raise ValueError(f"volpathmis does not support polarized variants (as stock); the active variant is "
                             f"{mi.variant()}")
        self.use_spectral_mis = props.get("use_spectral_mis", True)
        super().__init__(props, RatioWeights(self.use_spectral_mis))

    def describe(self) -> str:
        return f"{super().describe()}, use_spectral_mis={self.use_spectral_mis}"
