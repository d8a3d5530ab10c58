"""layerbvh_mitsuba: the Mitsuba 3 side of layerbvh; importing it registers the `layerbvh` integrator."""
import mitsuba as _mi

if _mi.variant() is None:
    _mi.set_variant("llvm_ad_rgb")

from .integrator import LayerBVHIntegrator, register  # noqa: E402

register()

__all__ = ["LayerBVHIntegrator", "register"]
