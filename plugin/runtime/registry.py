"""Our integrators registered with Mitsuba, once per JIT variant: `layerbvh` (the path tracer), `layerbvh_direct` (direct illumination), `layerbvh_volpath` and `layerbvh_volpathmis` (volumetric path tracing)."""
from __future__ import annotations

import mitsuba as mi

from layerbvh_mitsuba.runtime.direct import LayerBVHDirect
from layerbvh_mitsuba.runtime.integrator import LayerBVHPathTracer
from layerbvh_mitsuba.runtime.volpath import LayerBVHVolPath
from layerbvh_mitsuba.runtime.volpathmis import LayerBVHVolPathMIS

# Plugin name -> (the Mitsuba class's name, the Python class whose methods it takes).
PLUGINS = {"layerbvh": ("LayerBVHIntegrator", LayerBVHPathTracer),
           "layerbvh_direct": ("LayerBVHDirectIntegrator", LayerBVHDirect),
           "layerbvh_volpath": ("LayerBVHVolPathIntegrator", LayerBVHVolPath),
           "layerbvh_volpathmis": ("LayerBVHVolPathMISIntegrator", LayerBVHVolPathMIS)}
# Mitsuba's integrators ours stand in for, by plugin name.
STANDS_IN_FOR = {"path": "layerbvh", "direct": "layerbvh_direct", "volpath": "layerbvh_volpath",
                 "volpathmis": "layerbvh_volpathmis"}

_classes: dict[tuple[str, str], type] = {}


def handles_media(estimator: str) -> bool:
    """Whether ours standing in for Mitsuba's `estimator` renders participating media (VOLUMETRIC)."""
    return PLUGINS[STANDS_IN_FOR[estimator]][1].VOLUMETRIC


def is_jit_variant(variant: str | None) -> bool:
    return bool(variant) and variant.split("_", 1)[0] in ("llvm", "cuda")


def integrator_class(plugin: str = "layerbvh") -> type:
    """Our integrator `plugin` as a class of the active variant: that variant's
    mi.SamplingIntegrator with the Python class's methods (Mitsuba's base classes exist once per
    variant, and nanobind classes take a single base); `_base` is that SamplingIntegrator."""
    variant = mi.variant()
    if not is_jit_variant(variant):
        raise ValueError(f"the {plugin} integrator needs a JIT variant (llvm_* or cuda_*); the active variant is "
                         f"{variant}")
    cls = _classes.get((plugin, variant))
    if cls is None:
        name, py_cls = PLUGINS[plugin]
        methods = {}
        for klass in reversed(py_cls.__mro__[:-1]):  # base classes first, so subclasses override
            methods.update({k: v for k, v in vars(klass).items() if k not in ("__dict__", "__weakref__")})
        base = mi.SamplingIntegrator
        cls = _classes[(plugin, variant)] = type(name, (base,), {**methods, "_base": base})
    return cls


def register(variant: str | None = None) -> None:
    """Register our integrators with the active Mitsuba variant (a scalar variant gets factories
    that refuse by name: our traversal runs on Dr.Jit's JIT backends only)."""
    if (variant or mi.variant()) is not None:
        for plugin in PLUGINS:
            mi.register_integrator(plugin, lambda props, plugin=plugin: integrator_class(plugin)(props))
