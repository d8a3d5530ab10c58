"""layerbvh_mitsuba: the Mitsuba 3 side of layerbvh; once Mitsuba is imported (before or after this
package), our integrators (`layerbvh`, `layerbvh_direct`, `layerbvh_volpath`, `layerbvh_volpathmis`,
`layerbvh_depth`, `layerbvh_ptracer`, `layerbvh_prb`, `layerbvh_prb_basic`, `layerbvh_prbvolpath`:
runtime/registry.py PLUGINS; stock's `stokes`, `aov` and `moment` wrap them) are registered with
every variant set; `layerbvh_mitsuba.register()` does it explicitly.

Importing this package imports nothing heavy itself: pytest loads our plugin (`pytest_plugin`, an
entry point) in every run of a user's environment, and a run that never touches a scene should not
pay for Mitsuba, Dr.Jit and numba (issue 42: 1.1 s warm, 14.6 s the first time), nor break where
Mitsuba cannot be imported. So registration waits for Mitsuba: at once if it is imported already,
otherwise right after its import (a finder at the front of `sys.meta_path` that steps aside after
that one import).
"""
from __future__ import annotations

import importlib.util
import sys


def _on_variant_change(_old, new):
    if new is not None:
        from layerbvh_mitsuba.runtime.registry import register  # local: the integrators load with the first variant
        register(new)


def _hook(mi) -> None:
    """Register with the variant set now and with each one set later."""
    mi.detail.add_variant_callback(_on_variant_change)
    _on_variant_change(None, mi.variant())


class _AfterMitsuba:
    """A meta path finder (the protocol: importlib.abc costs 40 ms to import) that finds nothing;
    when `mitsuba` is imported, it wraps that one import so `_hook` runs right after Mitsuba's own
    module code, then leaves sys.meta_path."""

    def find_spec(self, name, path, target=None):
        if name != "mitsuba":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)  # (the other finders: this one is gone)
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            _hook(sys.modules[name])  # (Mitsuba puts a module of its own there)
        spec.loader.exec_module = exec_module
        return spec


if "mitsuba" in sys.modules:
    _hook(sys.modules["mitsuba"])
elif not any(isinstance(f, _AfterMitsuba) for f in sys.meta_path):
    sys.meta_path.insert(0, _AfterMitsuba())


def __getattr__(name):
    """`integrator_class` and `register` (runtime.registry), imported when first asked for."""
    if name in ("integrator_class", "register"):
        from layerbvh_mitsuba.runtime import registry  # local: Mitsuba and the engine load only when used
        return getattr(registry, name)
    raise AttributeError(f"module 'layerbvh_mitsuba' has no attribute {name!r}")


__all__ = ["integrator_class", "register"]
