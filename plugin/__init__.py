"""layerbvh_mitsuba: the Mitsuba 3 side of layerbvh; importing it registers the `layerbvh` integrator
with the active Mitsuba variant, and again with each variant set later (no variant is set here)."""
import mitsuba as _mi

from layerbvh_mitsuba.runtime.integrator import LayerBVHPathTracer, integrator_class, register


def _on_variant_change(_old, new):
    if new is not None:
        register(new)


register()
_mi.detail.add_variant_callback(_on_variant_change)

__all__ = ["LayerBVHPathTracer", "integrator_class", "register"]
