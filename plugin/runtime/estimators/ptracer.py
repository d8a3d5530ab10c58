"""Stock `ptracer`'s estimator (light paths traced from the emitters and splatted onto the film through the sensor),
every ray query ours. Follows src/integrators/ptracer.cpp @ v3.9.1."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime import draw_order
from layerbvh_mitsuba.runtime.estimators.common import Kinds, Tracing, loop, read_depths
from layerbvh_mitsuba.runtime.features import Features

# Stock's light paths reflect with the BSDF's adjoint (importance transport).
_IMPORTANCE = mi.TransportMode.Importance


class ParticleTracerEstimator:
    r"""Particle tracing: the estimator of stock ``ptracer``, an adjoint integrator. Its rays start
    at the emitters, as incoherent as rays get (issue 43): the paper's own case.

    Algorithm (stock's ``sample``; the render driver calls it once per pass with the pass's
    image block and ``sample_scale``, the film's normalisation):

    1. Emitters seen directly (unless ``hide_emitters`` or ``max_depth`` = 0): pick an emitter,
       sample a point on it (a direction from the sensor's position for an infinite one), sample
       the sensor's direction to it, test that connection for occlusion (ours) and splat the
       emitter's weight at the pixel it lands on (alpha 0).
    2. A light ray: ``scene.sample_emitter_ray`` (emitter, wavelength, direction, position).
    3. Its path: at each vertex it hits (ours), connect to the sensor (an occlusion test, ours;
       the BSDF evaluated adjoint, with the shading-normal correction of Veach's thesis, p. 155;
       splatted with alpha 1), then sample the BSDF in importance mode, drop paths that leak
       through a shading normal, apply the same correction to the throughput, and from
       ``rr_depth`` on play Russian roulette (survival ``min(max(throughput) eta^2, 0.95)``).
       A path of ``max_depth`` vertices (``-1``: unlimited) stops.

    The sampler is used in stock's order, which a same-seed render must follow draw for draw:
    per pass, [shutter 1D if the shutter is open for a while] emitter 1D, infinite-emitter 2D
    and finite-emitter 2D (both drawn in a JIT variant, where stock runs both branches), sensor
    2D, wavelength 1D (step 1, unless skipped: then none of them); [shutter 1D] wavelength 1D,
    direction 2D, position 2D (step 2); per path vertex: sensor 2D, the BSDF's 1D and 2D in
    the order stock's build evaluates ``bsdf->sample``'s arguments (GCC: right to left, the 2D
    first; probed from the wheel, runtime/draw_order.py), Russian roulette 1D (drawn at every
    vertex in a JIT variant, used from ``rr_depth``).
    Properties: ``max_depth`` (-1), ``rr_depth`` (5), ``hide_emitters`` (false); the adjoint
    base reads ``samples_per_pass``."""

    PLUGIN = "ptracer"
    VOLUMETRIC = False
    ADJOINT = True  # the driver is an mi.AdjointIntegrator: Mitsuba's render calls `sample` with an image block

    def __init__(self, props: mi.Properties):
        self.max_depth, self.rr_depth, self.hide_emitters = read_depths(props)

    def kinds(self, use: Features) -> Kinds:
        """Light rays (closest hit) and the sensor connections' occlusion tests."""
        return [(False, "light")] + ([(True, "shadow")] if self.max_depth != 0 else [])

    def auto_rule(self, use: Features) -> str | None:
        return None

    def prepass(self, scene, sensor, sampler, tr: Tracing) -> None:
        """auto's pre-pass: a light ray per lane of `sampler`, its first hit's sensor connection
        and the ray leaving it (what reaches every kind of batch a light path traces)."""
        ray, _ = self._light_ray(scene, sensor, sampler)
        pi = tr.queries.intersect(ray, dr.full(mi.Bool, True, dr.width(ray.o)), hint="light")
        si = tr.queries.surface(pi, ray, mi.RayFlags.All)
        hit = pi.is_valid()
        sensor_ds, _ = sensor.sample_direction(si, sampler.next_2d(), hit)
        tr.queries.occluded(tr.queries.shadow_ray(si, sensor_ds.p), hit & (sensor_ds.pdf > 0))
        s2 = sampler.next_2d(hit)
        bs, _ = si.bsdf(ray).sample(mi.BSDFContext(_IMPORTANCE), si, sampler.next_1d(hit), s2, hit)
        tr.queries.intersect(tr.queries.spawn(si, si.to_world(bs.wo)), hit, hint="light")

    def sample(self, scene, sensor, sampler, block, sample_scale, tr: Tracing) -> None:
        """One pass: every lane of `sampler` traces one light path into `block`."""
        if self.max_depth != 0 and not self.hide_emitters:
            self._visible_emitters(scene, sensor, sampler, block, sample_scale, tr)
        ray, throughput = self._light_ray(scene, sensor, sampler)
        active = dr.max(mi.unpolarized_spectrum(throughput)) != 0
        self._light_path(scene, sensor, sampler, ray, throughput, block, sample_scale, active, tr)

    # -- step 1: emitters the sensor sees directly ----------------------------------------------
    def _visible_emitters(self, scene, sensor, sampler, block, sample_scale, tr: Tracing) -> None:
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        idx, idx_weight, _ = scene.sample_emitter(sampler.next_1d())
        emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), idx)
        active = ~mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
        infinite = mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite)
        si = dr.zeros(mi.SurfaceInteraction3f)
        no_wavelengths = dr.zeros(type(si.wavelengths))
        # An infinite emitter: a direction seen from the sensor's position.
        ref = mi.Interaction3f(0.0, time, no_wavelengths, sensor.world_transform().translation())
        ds, _ = emitter.sample_direction(ref, sampler.next_2d(active), active & infinite)
        weight = dr.select(active & infinite,
                           mi.Spectrum(dr.select(ds.pdf > 0, dr.rcp(ds.pdf), 0.0) * dr.square(ds.dist)), 0.0)
        si = dr.select(active & infinite, mi.SurfaceInteraction3f(ds, ref.wavelengths), si)
        # A finite one: a point on it.
        ps, pos_weight = emitter.sample_position(time, sampler.next_2d(active), active & ~infinite)
        weight = dr.select(active & ~infinite, mi.Spectrum(pos_weight), weight)
        si = dr.select(active & ~infinite, mi.SurfaceInteraction3f(ps, no_wavelengths), si)
        sensor_ds, sensor_weight = sensor.sample_direction(si, sampler.next_2d(), active)
        si.wi = sensor_ds.d
        si.wavelengths, wav_weight = emitter.sample_wavelengths(si, sampler.next_1d(active), active)
        si.shape = emitter.get_shape()
        self._connect(scene, si, sensor_ds, None, idx_weight * weight * wav_weight * sensor_weight, block,
                      sample_scale, active, tr)

    # -- step 2: the light ray ------------------------------------------------------------------
    @staticmethod
    def _light_ray(scene, sensor, sampler):
        time = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength_sample = sampler.next_1d()
        direction_sample = sampler.next_2d()
        position_sample = sampler.next_2d()
        ray, weight, _ = scene.sample_emitter_ray(time, wavelength_sample, direction_sample, position_sample, True)
        return ray, weight

    # -- step 3: its path, a sensor connection at every vertex ----------------------------------
    def _light_path(self, scene, sensor, sampler, ray, throughput, block, sample_scale, active, tr: Tracing) -> None:
        max_depth, rr_depth, queries = self.max_depth, self.rr_depth, tr.queries
        depth, eta = mi.Int32(1), mi.Float(1.0)
        pi = queries.intersect(ray, active, hint="light")
        active &= pi.is_valid()
        if max_depth >= 0:
            active &= depth < max_depth

        def body(active, depth, ray, throughput, pi, eta, sampler):
            tr.iteration()
            si = tr.queries.surface(pi, ray, mi.RayFlags.All)
            bsdf = si.bsdf(ray)
            sensor_ds, sensor_weight = sensor.sample_direction(si, sampler.next_2d(), active)
            self._connect(scene, si, sensor_ds, bsdf, throughput * sensor_weight, block, sample_scale, active, tr)
            s1, s2 = draw_order.draws(sampler, active)  # (stock's order: see the class docstring)
            bs, bsdf_val = bsdf.sample(mi.BSDFContext(_IMPORTANCE), si, s1, s2, active)
            # Light leaks through shading normals are dropped; the adjoint's correction (Veach, p. 155).
            wi_dot_n, wo_dot_n = dr.dot(si.n, -ray.d), dr.dot(si.n, si.to_world(bs.wo))
            active &= (wi_dot_n * mi.Frame3f.cos_theta(si.wi) > 0) & (wo_dot_n * mi.Frame3f.cos_theta(bs.wo) > 0)
            correction = dr.abs((mi.Frame3f.cos_theta(si.wi) * wo_dot_n) / (mi.Frame3f.cos_theta(bs.wo) * wi_dot_n))
            throughput *= bsdf_val * correction
            eta *= bs.eta
            active &= dr.any(mi.unpolarized_spectrum(throughput) != 0)
            depth += 1
            if max_depth >= 0:
                active &= depth < max_depth
            use_rr = depth > rr_depth
            q = dr.minimum(dr.max(mi.unpolarized_spectrum(throughput)) * dr.square(eta), 0.95)
            active = dr.select(use_rr, active & (sampler.next_1d(active) < q), active)
            throughput = dr.select(use_rr, throughput * dr.rcp(q), throughput)
            ray = queries.spawn(si, si.to_world(bs.wo))
            pi = queries.intersect(ray, active, hint="light")
            return active & pi.is_valid(), depth, ray, throughput, pi, eta, sampler

        loop((active, depth, ray, throughput, pi, eta, sampler), cond=lambda active, *_: active, body=body,
             symbolic=tr.megakernel, label="layerbvh ptracer")

    def _connect(self, scene, si, sensor_ds, bsdf, weight, block, sample_scale, active, tr: Tracing) -> None:
        """Splat `weight` at the pixel the sensor sees `si` through, if nothing blocks the way
        (ours): an emitter's point (`bsdf` None: foreshortening only, alpha 0) or a path vertex
        (its BSDF toward the sensor, adjoint-corrected, alpha 1)."""
        active = active & (sensor_ds.pdf > 0) & dr.any(mi.unpolarized_spectrum(weight) != 0)
        sensor_ray = tr.queries.shadow_ray(si, sensor_ds.p)
        active &= ~tr.queries.occluded(sensor_ray, active)
        local_d = si.to_local(sensor_ray.d)
        cos_d = mi.Frame3f.cos_theta(local_d)
        # (null pointers compared as stock compares them; an emitter's point has no BSDF at all)
        no_bsdf = mi.Bool(True) if bsdf is None else bsdf == None  # noqa: E711
        on_surface = active & (si.shape != None)  # noqa: E711
        surface_weight = dr.select(on_surface & no_bsdf, dr.maximum(0.0, cos_d), 1.0)  # an emitter's foreshortening
        if bsdf is not None:
            on_surface &= ~no_bsdf
            wi_dot_n, wo_dot_n = dr.dot(si.n, si.to_world(si.wi)), dr.dot(si.n, sensor_ray.d)
            valid = (wi_dot_n * mi.Frame3f.cos_theta(si.wi) > 0) & (wo_dot_n * cos_d > 0)
            correction = dr.select(valid, dr.abs((mi.Frame3f.cos_theta(si.wi) * wo_dot_n) / (cos_d * wi_dot_n)), 0.0)
            value = correction * bsdf.eval(mi.BSDFContext(_IMPORTANCE), si, local_d, on_surface)
            surface_weight = dr.select(on_surface, surface_weight * value, mi.Spectrum(surface_weight))
        # An infinite emitter (no shape) seen from its far side adds nothing.
        behind = active & (si.shape == None) & no_bsdf & (cos_d <= 0)  # noqa: E711
        surface_weight = dr.select(behind, 0.0, mi.Spectrum(surface_weight))
        alpha = mi.Float(0.0) if bsdf is None else dr.select(no_bsdf, 0.0, 1.0)
        block.put(sensor_ds.uv + block.offset(), si.wavelengths, weight * surface_weight * sample_scale, alpha, 0.0,
                  active)

    def describe(self) -> str:
        return f"ptracer, max_depth={self.max_depth}, rr_depth={self.rr_depth}"
