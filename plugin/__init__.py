"""layerbvh_mitsuba: the Mitsuba 3 side of layerbvh; importing it registers our integrators (`layerbvh`, `layerbvh_direct`)
with the active Mitsuba variant, and again with each variant set later (no variant is set here)."""
import mitsuba as _mi

from layerbvh_mitsuba.runtime.direct import LayerBVHDirect
from layerbvh_mitsuba.runtime.integrator import LayerBVHPathTracer
from layerbvh_mitsuba.runtime.registry import integrator_class, register


def _on_variant_change(_old, new):
    if new is not None:
        register(new)


register()
_mi.detail.add_variant_callback(_on_variant_change)

__all__ = ["LayerBVHDirect", "LayerBVHPathTracer", "integrator_class", "register"]
