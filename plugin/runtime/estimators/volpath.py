"""Stock `volpath`'s estimator (volumetric path tracing with participating media): the shared walk (media.MediaWalk)
with a path weight that is a throughput. Follows src/integrators/volpath.cpp @ v3.9.1."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import mis_weight, unit_throughput
from layerbvh_mitsuba.runtime.estimators.media import MediaWalk, index_spectrum


def _unpolarized(x):
    return mi.unpolarized_spectrum(x)


def _scaled(w: mi.Spectrum, factor) -> mi.Spectrum:
    """A throughput times a per-wavelength factor (mi.UnpolarizedSpectrum: a transmittance, a
    medium's coefficient), as stock's `Spectrum * UnpolarizedSpectrum`. Polarized variants: the
    factor as a Mueller matrix (mi.Spectrum of it is the factor times the identity), since
    Dr.Jit's Python arrays have no product of the two types."""
    return w * (mi.Spectrum(factor) if mi.is_polarized else factor)


@dataclass
class Throughput:
    """volpath's path weight, in the walk's state (stock LoopState's two fields)."""

    throughput: mi.Spectrum
    last_scatter_direction_pdf: mi.Float  # for the MIS weight of emission found by a sampled direction


class Transmittance:
    """volpath's shadow-ray weights: the transmittance, a spectrum, as stock's ratio tracking
    updates it at each free flight, null collision and null surface (volpathmis keeps p/f ratios
    instead: volpathmis.ShadowRatios, the same four operations)."""

    @staticmethod
    def free_flight(w, tr, free_flight_pdf, channel, is_spectral):
        tr_pdf = index_spectrum(free_flight_pdf, channel)
        return dr.select(is_spectral, _scaled(w, dr.select(tr_pdf > 0, tr / tr_pdf, 0)), w)

    @staticmethod
    def null_collision(w, mei, channel, is_spectral, not_spectral):
        w = dr.select(is_spectral, _scaled(w, mei.sigma_n), w)
        return dr.select(not_spectral, _scaled(w, mei.sigma_n / mei.combined_extinction), w)

    @staticmethod
    def null_surface(w, bsdf_val, si, channel, active):
        return dr.select(active, w * si.to_world_mueller(bsdf_val, si.wi, si.wi), w)

    @staticmethod
    def passes(w):
        return dr.any(_unpolarized(w) != 0)


class ThroughputWeights:
    """How each event of the walk changes volpath's `Throughput` (the strategy media.MediaWalk
    calls; volpathmis.RatioWeights is the other)."""

    shadow = Transmittance

    @staticmethod
    def start(n: int) -> Throughput:
        return Throughput(throughput=unit_throughput(n), last_scatter_direction_pdf=dr.full(mi.Float, 1, n))

    @staticmethod
    def copy(w: Throughput) -> Throughput:
        return w

    @staticmethod
    def roulette(sampler, w: Throughput, active, depth, eta, rr_depth: int, channel):
        """On the throughput, past rr_depth (`next_1d`); a path of zero throughput ends first."""
        throughput = w.throughput
        active &= dr.any(_unpolarized(throughput) != 0)
        q = dr.minimum(dr.max(_unpolarized(throughput)) * dr.square(eta), 0.95)
        perform_rr = depth > rr_depth
        active &= (sampler.next_1d(active) < q) | ~perform_rr
        throughput = dr.select(perform_rr, throughput * dr.rcp(dr.detach(q)), throughput)
        return active, Throughput(throughput, w.last_scatter_direction_pdf)

    @staticmethod
    def free_flight(w: Throughput, tr, free_flight_pdf, channel, is_spectral) -> Throughput:
        return Throughput(Transmittance.free_flight(w.throughput, tr, free_flight_pdf, channel, is_spectral),
                          w.last_scatter_direction_pdf)

    @staticmethod
    def null_collision(w: Throughput, mei, null_scatter_prob, channel, spectral, plain, null) -> Throughput:
        return Throughput(dr.select(spectral, _scaled(w.throughput, mei.sigma_n / null_scatter_prob), w.throughput),
                          w.last_scatter_direction_pdf)

    @staticmethod
    def real_collision(w: Throughput, mei, null_scatter_prob, channel, spectral, plain) -> Throughput:
        throughput = dr.select(spectral, _scaled(w.throughput, mei.sigma_s
                               / dr.mean(mei.sigma_t / mei.combined_extinction, axis=0)), w.throughput)
        throughput = dr.select(plain, _scaled(throughput, mei.sigma_s / mei.sigma_t), throughput)
        return Throughput(throughput, w.last_scatter_direction_pdf)

    @staticmethod
    def scattered_in_medium(w: Throughput, scattered) -> Throughput:
        return w

    @staticmethod
    def phase_sampled(w: Throughput, phase_weight, phase_pdf, channel, scattered):
        """A phase sample of pdf 0 ends the path there."""
        scattered &= phase_pdf > 0
        return scattered, Throughput(dr.select(scattered, w.throughput * phase_weight, w.throughput),
                                     dr.select(scattered, phase_pdf, w.last_scatter_direction_pdf))

    @staticmethod
    def surface_emission(w: Throughput, emitted, emitter_pdf, count_direct, channel, active):
        t = w.throughput
        return dr.select(count_direct, t * emitted,
                         t * mis_weight(w.last_scatter_direction_pdf, emitter_pdf) * emitted), w

    @staticmethod
    def eval_bsdf(bsdf, ctx, si, ds, active):
        wo = si.to_local(ds.d)
        return si.to_world_mueller(bsdf.eval(ctx, si, wo, active), -wo, si.wi), bsdf.pdf(ctx, si, wo, active)

    @staticmethod
    def emitter_start(w: Throughput, ds, emitter_weight, channel, active):
        """(the emitter's value over its pdf, no weights before the walk)."""
        return dr.select(ds.pdf == 0, 0, emitter_weight), None

    @staticmethod
    def shadow_start(shadow_w, active):
        return unit_throughput(dr.width(active))

    @staticmethod
    def direct(w: Throughput, transmittance, emitter_val, f, pdf, ds, channel, active, on_surface: bool):
        """Emitter sampling's contribution: throughput x f (phase or BSDF) x emitted light x the
        power heuristic against sampling f (stock's products, in stock's order)."""
        emitted = emitter_val if transmittance is None else transmittance * emitter_val
        mis = mis_weight(ds.pdf, dr.select(ds.delta, 0, pdf))
        return w.throughput * f * mis * emitted if on_surface else w.throughput * f * emitted * mis

    @staticmethod
    def bsdf_sampled(w: Throughput, bs, bsdf_weight, si, channel, active):
        bsdf_weight = si.to_world_mueller(bsdf_weight, -bs.wo, si.wi)
        return active, None, Throughput(dr.select(active, w.throughput * bsdf_weight, w.throughput),
                                        w.last_scatter_direction_pdf)

    @staticmethod
    def surface_scattered(w: Throughput, bs, bsdf_weight, channel, active, non_null) -> Throughput:
        return Throughput(w.throughput, dr.select(non_null, bs.pdf, w.last_scatter_direction_pdf))


class VolPathEstimator(MediaWalk):
    """Volumetric path tracing: the estimator of stock ``volpath`` (the walk and its sampler use:
    media.MediaWalk), its path weight a throughput (``ThroughputWeights``). Properties:
    ``max_depth`` (-1, infinite), ``rr_depth`` (5), ``hide_emitters`` (false) as in ``volpath``."""

    PLUGIN = "volpath"

    def __init__(self, props: mi.Properties):
        super().__init__(props, ThroughputWeights)
