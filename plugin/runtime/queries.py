"""The bounce loop's one interface to ray queries (`RayQueries`), and the two answers that run inside its kernel: our
per_ray traversal inline, and Mitsuba's Embree (the control)."""
from __future__ import annotations

from abc import ABC, abstractmethod


class RayQueries(ABC):
    """Closest hit and occlusion of a batch of Mitsuba rays, answered as Mitsuba answers them
    (`mi.PreliminaryIntersection3f`, `mi.Bool`). `symbolic`: the queries can be recorded inside
    a symbolic Dr.Jit loop (one kernel); otherwise they synchronise with the host (our wavefront
    traversal) and the loop runs in Python. `hint` names the kind of batch ("camera", "bounce"):
    auto decides per kind; `kind` (record.KINDS codes) labels the rays for a recorder."""

    symbolic: bool = False

    @abstractmethod
    def intersect(self, ray, active, hint: str = "camera", kind=None):
        """Closest hit of every active ray."""

    @abstractmethod
    def occluded(self, ray, active):
        """Whether anything lies on each active ray in (0, ray.maxt)."""

    def surface(self, pi, ray, flags, active=True):
        """The surface interaction of a closest hit: stock's `pi.compute_surface_interaction`,
        which every estimator calls through here so that our tracer can repair the normals that
        Mitsuba loses to float32 range (runtime/normals.py)."""
        return pi.compute_surface_interaction(ray, flags, active)

    def shadow_ray(self, ref, p):
        """The ray from interaction `ref` to point `p` (stock's `ref.spawn_ray_to(p)`), through here
        for the same reason as `surface`."""
        return ref.spawn_ray_to(p)

    def spawn(self, si, d):
        """The ray leaving surface interaction `si` along `d` (stock's `si.spawn_ray(d)`), through
        here for the same reason as `surface`."""
        return si.spawn_ray(d)


class InlineQueries(RayQueries):
    """Our per_ray traversal inside the caller's kernel (the megakernel path)."""

    symbolic = True

    def __init__(self, tracer):
        self.tracer = tracer  # adapter.SceneTracer

    def intersect(self, ray, active, hint: str = "camera", kind=None):
        return self.tracer.intersect_inline(ray, active)

    def occluded(self, ray, active):
        return self.tracer.occluded_inline(ray, active)

    def surface(self, pi, ray, flags, active=True):
        return self.tracer.surface(pi, ray, flags, active)

    def shadow_ray(self, ref, p):
        return self.tracer.shadow_ray(ref, p)

    def spawn(self, si, d):
        return self.tracer.spawn(si, d)


class EmbreeQueries(RayQueries):
    """Stock Mitsuba's (Embree's) queries: the control that isolates the traversal's cost (same
    loop, another traversal)."""

    symbolic = True

    def __init__(self, scene):
        self.scene = scene

    def intersect(self, ray, active, hint: str = "camera", kind=None):
        return self.scene.ray_intersect_preliminary(ray, coherent=hint == "camera", active=active)

    def occluded(self, ray, active):
        return self.scene.ray_test(ray, active)
