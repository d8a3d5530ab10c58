"""Our integrators registered with Mitsuba, once per JIT variant: `layerbvh` (path), `layerbvh_direct`,
`layerbvh_volpath`, `layerbvh_volpathmis`, `layerbvh_depth`, `layerbvh_ptracer`, `layerbvh_prb`, `layerbvh_prb_basic`
and `layerbvh_prbvolpath`, each the render driver given one estimator."""
from __future__ import annotations

import mitsuba as mi

from layerbvh_mitsuba.runtime.driver import driver_class
from layerbvh_mitsuba.runtime.estimators.depth import DepthEstimator
from layerbvh_mitsuba.runtime.estimators.direct import DirectEstimator
from layerbvh_mitsuba.runtime.estimators.path import PathEstimator
from layerbvh_mitsuba.runtime.estimators.prb import PRBEstimator
from layerbvh_mitsuba.runtime.estimators.prb_basic import BasicPRBEstimator
from layerbvh_mitsuba.runtime.estimators.prbvolpath import PRBVolPathEstimator
from layerbvh_mitsuba.runtime.estimators.ptracer import ParticleTracerEstimator
from layerbvh_mitsuba.runtime.estimators.volpath import VolPathEstimator
from layerbvh_mitsuba.runtime.estimators.volpathmis import VolPathMISEstimator

# Plugin name -> (the Mitsuba class's name, its estimator). One line per estimator.
PLUGINS = {"layerbvh": ("LayerBVHIntegrator", PathEstimator),
           "layerbvh_direct": ("LayerBVHDirectIntegrator", DirectEstimator),
           "layerbvh_volpath": ("LayerBVHVolPathIntegrator", VolPathEstimator),
           "layerbvh_volpathmis": ("LayerBVHVolPathMISIntegrator", VolPathMISEstimator),
           "layerbvh_depth": ("LayerBVHDepthIntegrator", DepthEstimator),
           "layerbvh_ptracer": ("LayerBVHParticleTracerIntegrator", ParticleTracerEstimator),
           "layerbvh_prb": ("LayerBVHPRBIntegrator", PRBEstimator),
           "layerbvh_prb_basic": ("LayerBVHBasicPRBIntegrator", BasicPRBEstimator),
           "layerbvh_prbvolpath": ("LayerBVHPRBVolPathIntegrator", PRBVolPathEstimator)}
# Mitsuba's integrators ours stand in for, by plugin name (each estimator names the one it mirrors).
STANDS_IN_FOR = {estimator.PLUGIN: plugin for plugin, (_, estimator) in PLUGINS.items()}

_classes: dict[tuple[str, str], type] = {}


def handles_media(estimator: str) -> bool:
    """Whether ours standing in for Mitsuba's `estimator` renders participating media (VOLUMETRIC)."""
    return PLUGINS[STANDS_IN_FOR[estimator]][1].VOLUMETRIC


def sampling(estimator: str) -> bool:
    """Whether ours standing in for Mitsuba's `estimator` is a plain sampling integrator (one that
    Mitsuba's aov, moment and stokes wrappers can run): not adjoint, not differentiable."""
    cls = PLUGINS[STANDS_IN_FOR[estimator]][1]
    return not getattr(cls, "ADJOINT", False) and not getattr(cls, "DIFFERENTIABLE", False)


def differentiation(estimator: str) -> tuple[bool, bool]:
    """(whether ours standing in for Mitsuba's `estimator` renders derivatives, whether in
    forward mode too); (False, False) for an integrator we do not mirror."""
    cls = PLUGINS[STANDS_IN_FOR[estimator]][1] if estimator in STANDS_IN_FOR else None
    diff = bool(getattr(cls, "DIFFERENTIABLE", False))
    return diff, diff and bool(getattr(cls, "FORWARD", True))


def is_jit_variant(variant: str | None) -> bool:
    return bool(variant) and variant.split("_", 1)[0] in ("llvm", "cuda")


def integrator_class(plugin: str = "layerbvh") -> type:
    """Our integrator `plugin` as a class of the active variant: a subclass naming its estimator
    (`ESTIMATOR`) of the render driver (driver.driver_class) over that variant's
    mi.SamplingIntegrator; over mi.AdjointIntegrator for an estimator that is ADJOINT, whose
    `sample` is then the driver's `sample_adjoint`; over Mitsuba's Python RBIntegrator for one
    that is DIFFERENTIABLE, whose `sample` is `sample_differentiable` and whose render,
    render_forward and render_backward are Mitsuba's, held (held_instances)."""
    variant = mi.variant()
    if not is_jit_variant(variant):
        raise ValueError(f"the {plugin} integrator needs a JIT variant (llvm_* or cuda_*); the active variant is "
                         f"{variant}")
    cls = _classes.get((plugin, variant))
    if cls is None:
        name, estimator = PLUGINS[plugin]
        if getattr(estimator, "ADJOINT", False):
            driver = driver_class(mi.AdjointIntegrator)
            names = {"sample": driver.sample_adjoint}
        elif getattr(estimator, "DIFFERENTIABLE", False):
            # (Mitsuba reloads its Python integrators per variant: this variant's RBIntegrator.)
            from mitsuba.ad.integrators.common import RBIntegrator  # local: exists once a JIT variant is set
            driver = driver_class(RBIntegrator)
            names = {"sample": driver.sample_differentiable, "render": driver.render_differentiable,
                     "render_forward": driver.render_forward_held,
                     "render_backward": driver.render_backward_held}
        else:
            driver, names = driver_class(mi.SamplingIntegrator), {}
        cls = _classes[(plugin, variant)] = type(name, (driver,), {**names, "ESTIMATOR": estimator, "PLUGIN": plugin})
    return cls


def register(variant: str | None = None) -> None:
    """Register our integrators with the active Mitsuba variant (a scalar variant gets factories
    that refuse by name: our traversal runs on Dr.Jit's JIT backends only)."""
    if (variant or mi.variant()) is not None:
        for plugin in PLUGINS:
            mi.register_integrator(plugin, lambda props, plugin=plugin: integrator_class(plugin)(props))
