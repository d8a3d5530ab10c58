"""Stock `direct`'s estimator (direct illumination: emitter and BSDF sampling combined by MIS), every ray through the
given queries. Follows src/integrators/direct.cpp @ v3.9.1."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime import draw_order
from layerbvh_mitsuba.runtime.estimators.common import Kinds, Tracing, loop, mis_weight, skip_area_emitters
from layerbvh_mitsuba.runtime.features import Features
from layerbvh_mitsuba.runtime.record import bounce_kind


class DirectEstimator:
    r"""Direct illumination: the estimator of stock ``direct``.

    Algorithm (stock ``direct``'s ``sample``): find the camera ray's hit with a closest-hit query
    and add the emission seen there (unless ``hide_emitters``). At a hit, for each of
    ``emitter_samples`` samples draw ``next_2d``, sample an emitter direction, test its visibility
    with an any-hit query and add the BSDF-weighted emission, MIS-weighted against BSDF sampling
    (a delta emitter: weight 1); then for each of ``bsdf_samples`` samples draw ``next_2d`` and
    ``next_1d``, sample the BSDF, trace the sampled direction with a closest-hit query and add the
    emission it reaches, MIS-weighted against emitter sampling. Sampler use is in exactly this
    order, and every sample is drawn on every lane (as a JIT render of stock draws them), so a
    same-seed render matches stock ``direct`` up to floating-point noise.

    There is no bounce loop: in the megakernel a render is one kernel, between kernels a few
    queries. The feature plan leaves out the shadow rays of a scene without emitters and the BSDF
    rays of one where nothing hit can emit (their samples are still drawn).

    Properties: ``shading_samples`` (1; sets both), ``emitter_samples``, ``bsdf_samples`` and
    ``hide_emitters`` as in ``direct``."""

    PLUGIN = "direct"
    VOLUMETRIC = False

    def __init__(self, props: mi.Properties):
        if "shading_samples" in props and ("emitter_samples" in props or "bsdf_samples" in props):
            raise ValueError("give shading_samples, or emitter_samples and/or bsdf_samples, not both")
        self.hide_emitters = props.get("hide_emitters", False)
        shading = props.get("shading_samples", 1)
        self.emitter_samples = props.get("emitter_samples", shading)
        self.bsdf_samples = props.get("bsdf_samples", shading)
        if min(self.emitter_samples, self.bsdf_samples) < 0 or self.emitter_samples + self.bsdf_samples == 0:
            raise ValueError(f"needs at least one emitter or BSDF sample and none negative, got "
                             f"emitter_samples={self.emitter_samples}, bsdf_samples={self.bsdf_samples}")
        total = self.emitter_samples + self.bsdf_samples
        # Stock direct's weights: each strategy's share of the samples, and 1 / its sample count.
        self.frac_lum, self.frac_bsdf = self.emitter_samples / total, self.bsdf_samples / total
        self.weight_lum = 1 / self.emitter_samples if self.emitter_samples else 0.0
        self.weight_bsdf = 1 / self.bsdf_samples if self.bsdf_samples else 0.0

    def kinds(self, use: Features) -> Kinds:
        kinds = [(False, "camera")]
        if self.bsdf_samples and use.emitter_hits.on:
            kinds.append((False, "bounce"))
        if self.emitter_samples and use.emitter_sampling.on:
            kinds.append((True, "shadow"))
        return kinds

    def auto_rule(self, use: Features) -> str | None:
        return None

    def prepass(self, scene, sampler, cam: mi.Ray3f, tr: Tracing) -> None:
        """auto's pre-pass: the estimator itself on camera rays `cam` (every kind it traces)."""
        self.sample(scene, sampler, cam, None, dr.full(mi.Bool, True, dr.width(cam.o)), tr)

    def sample(self, scene, sampler, ray: mi.Ray3f, medium, active, tr: Tracing):
        """(radiance, valid) seen along the camera rays `ray`."""
        queries, use = tr.queries, tr.use
        n = dr.width(ray.o)
        tr.iteration()

        # Visible emitters.
        pi = queries.intersect(ray, active, hint="camera")
        if self.hide_emitters:  # as stock: a camera ray that hits an area emitter continues behind it
            pi = skip_area_emitters(queries, ray, pi, active, tr.megakernel)
        si = queries.surface(pi, ray, mi.RayFlags.All, active)
        valid_ray = active & si.is_valid()
        result = mi.Spectrum(0)
        if not self.hide_emitters:
            result += si.emitter(scene, active).eval(si, active)
        active &= si.is_valid()
        if not tr.megakernel:
            # Between kernels: the emission seen here goes into a kernel of its own. (Measured: with
            # emitter_samples 0 the camera hit's and the BSDF ray's Emitter::eval calls otherwise
            # meet in one kernel, where Dr.Jit 1.5's LLVM backend emitted their identical callable
            # twice after other renders in the process and LLVM refused it: "invalid redefinition
            # of function", an abort.)
            dr.eval(result)

        # Each strategy's samples run as a loop (`common.loop`): in the megakernel one symbolic
        # loop, each BSDF or emitter call recorded once; between kernels, the running sum is
        # evaluated after every sample. (Measured: unrolled, two samples' Emitter calls met in one
        # kernel, where Dr.Jit 1.5's LLVM backend emitted their identical callable twice after
        # other renders in the process and LLVM refused it, an abort.)
        ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)
        sample_emitter = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)

        def emitter_sample(sampler, i, result):
            """Emitter sampling: the shadow ray through our any-hit traversal (stock's visibility
            test is switched off: it would trace with Embree)."""
            active_e = mi.Bool(sample_emitter)
            em_sample = sampler.next_2d(active_e)
            if not use.emitter_sampling.on:
                return sampler, i + 1, result  # no emitter: nothing to add (the sample is drawn all the same)
            ds, emitter_val = scene.sample_emitter_direction(si, em_sample, False, active_e)
            active_e &= ds.pdf != 0.0
            active_e &= ~queries.occluded(queries.shadow_ray(si, ds.p), active_e)
            wo = si.to_local(ds.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, active_e)
            bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi)
            mis = dr.select(ds.delta, 1.0, mis_weight(ds.pdf * self.frac_lum, bsdf_pdf * self.frac_bsdf)
                            * self.weight_lum)
            return sampler, i + 1, dr.select(active_e, result + mis * bsdf_val * emitter_val, result)

        def bsdf_sample(sampler, i, result):
            """BSDF sampling: the sampled direction through our closest-hit traversal."""
            # Stock passes next_1d() and next_2d() as arguments of one call, whose evaluation order
            # its compiler chose (GCC: right to left): drawn in the order probed from the wheel.
            sample_1, sample_2 = draw_order.draws(sampler, active)
            bs, bsdf_val = bsdf.sample(ctx, si, sample_1, sample_2, active)
            if not use.emitter_hits.on:
                return sampler, i + 1, result  # nothing a ray reaches emits (the samples are drawn all the same)
            bsdf_val = si.to_world_mueller(bsdf_val, -bs.wo, si.wi)
            active_b = active & dr.any(mi.unpolarized_spectrum(bsdf_val) != 0)
            bray = queries.spawn(si, si.to_world(bs.wo))
            kind = bounce_kind(mi, dr, bs.sampled_type, 0) if tr.recording else None
            si_b = queries.surface(queries.intersect(bray, active_b, hint="bounce", kind=kind), bray, mi.RayFlags.All,
                                   active_b)
            emitter = si_b.emitter(scene, active_b)
            active_b &= emitter != None  # noqa: E711  (a Dr.Jit pointer array against null)
            emitter_val = emitter.eval(si_b, active_b)
            ds = mi.DirectionSample3f(scene, si=si_b, ref=si)
            emitter_pdf = dr.select(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), 0.0,
                                    scene.pdf_emitter_direction(si, ds, active_b))
            weight = mis_weight(bs.pdf * self.frac_bsdf, emitter_pdf * self.frac_lum) * self.weight_bsdf
            return sampler, i + 1, dr.select(active_b, result + bsdf_val * emitter_val * weight, result)

        for count, step, label in ((self.emitter_samples, emitter_sample, "emitter samples"),
                                   (self.bsdf_samples, bsdf_sample, "BSDF samples")):
            if count:
                sampler, _, result = loop((sampler, dr.zeros(mi.UInt32, n), result),
                                          cond=lambda sampler, i, result, count=count: i < count, body=step,
                                          symbolic=tr.megakernel, label=f"layerbvh_direct {label}")

        return result, valid_ray

    def describe(self) -> str:
        return f"emitter_samples={self.emitter_samples}, bsdf_samples={self.bsdf_samples}"
