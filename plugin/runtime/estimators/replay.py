"""What the path-replay estimators (prb, prb_basic) share: the derivative half of a vertex, where the detached
radiance a path carries is re-attached to the scene's parameters and pushed forward or back (Vicini et al. 2021,
"Path Replay Backpropagation", sec. 4)."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from layerbvh_mitsuba.runtime.estimators.common import Tracing, skip_area_emitters, unit_throughput


def area_jacobian(o, p, n, active):
    """Mitsuba's solid-angle to area Jacobian (its Python AD integrators' common.py, which exists
    once a JIT variant is set, and is reloaded per variant)."""
    from mitsuba.ad.integrators.common import solid_angle_to_area_jacobian  # local: exists once a variant is set
    return solid_angle_to_area_jacobian(o, p, n, active)


def differential(mode) -> bool:
    """Whether `mode` (a dr.ADMode) replays a path for its derivatives (not the primal image)."""
    return mode != dr.ADMode.Primal


@dataclass
class PathReplay:
    """What a replayed path carries from one vertex to the next (prb_basic's loop state; prb's
    adds to it)."""

    ray: mi.Ray3f                          # the ray that found `pi`
    pi: mi.PreliminaryIntersection3f       # the vertex to shade next
    ray_prev: mi.Ray3f                     # the ray that found the previous vertex
    pi_prev: mi.PreliminaryIntersection3f  # (its motion turns this vertex's wi)
    active: mi.Bool
    depth: mi.UInt32
    L: mi.Spectrum                         # radiance: summed (primal), or what remains of it (replay)
    dL: mi.Spectrum                        # the adjoint radiance (backward) or the derivative so far (forward)
    beta: mi.Spectrum                      # throughput

    @classmethod
    def begin(cls, mode, ray, pi, active, dL=None, state_in=None, **more):
        """The state of paths whose camera rays `ray` found `pi` (`state_in`: the primal pass's
        L; `more`: a subclass's own fields)."""
        n = dr.width(active)
        return cls(ray=mi.Ray3f(ray), pi=pi, ray_prev=mi.Ray3f(ray), pi_prev=dr.zeros(mi.PreliminaryIntersection3f, n),
                   active=mi.Bool(active), depth=dr.zeros(mi.UInt32, n),
                   L=dr.zeros(mi.Spectrum, n) if not differential(mode) else mi.Spectrum(state_in),
                   dL=dr.zeros(mi.Spectrum, n) if dL is None else mi.Spectrum(dL), beta=unit_throughput(n),
                   **more)


def camera_hits(tr: Tracing, ray, active, hide_emitters: bool):
    """The camera rays' first vertices (past area emitters with hide_emitters, as prb)."""
    pi = tr.queries.intersect(ray, active, hint="camera")
    return skip_area_emitters(tr.queries, ray, pi, active, tr.megakernel) if hide_emitters else pi


def reattached_reflection(queries, L, si, bsdf, ray_next, pi_next, active_next, flags):
    """The radiance reflected at vertex `si` with its derivatives attached: `L`, the detached
    radiance still to come along the path, scaled by the relative derivative of BSDF x cosine in the
    sampled direction, and by that of the solid-angle to area Jacobian where the next vertex
    `pi_next` (found by `ray_next`) moves. That next vertex is computed detached (only the current
    one's motion counts), the rest with derivatives. `flags`: what the next vertex's surface
    interaction computes (prb: Minimal; prb_basic: All), through `queries` (RayQueries.surface)."""
    si_next = queries.surface(pi_next, ray_next, flags, active_next)
    with dr.resume_grad():
        J = area_jacobian(si.p, si_next.p, si_next.n, active_next & si_next.is_valid())
        # The direction re-derived from the two vertices, so a moving vertex turns the cosine.
        toward = dr.select(si_next.is_valid(), dr.normalize(si_next.p - si.p), ray_next.d)
        wo = si.to_local(dr.replace_grad(ray_next.d, toward))
        f = bsdf.eval(mi.BSDFContext(), si, wo, active_next)
        return L * dr.relative_grad(f) * dr.relative_grad(J)


def propagate(mode, dL, Lo, active, megakernel: bool):
    """Push the attached contribution `Lo` of the active lanes: backward, from the adjoint
    radiance `dL` to the parameters' gradients; forward, from the parameters' gradients into
    `dL`, which is returned. A contribution with nothing attached is refused by name, as stock
    prb refuses it (a parameter without dr.enable_grad, usually).

    Forward in the wavefront loop keeps the parameters' gradients: Dr.Jit's default clears them
    once pushed, which in a symbolic loop (stock's, our megakernel) happens once, while the body
    is recorded, but in a Python loop after the first vertex, so every later vertex would push
    nothing (measured: 80% of a Cornell box's derivative pixels wrong). It keeps interior
    gradients too (ClearEdges only), and backward keeps the edges it crosses (ClearVertices):
    a parameter the scene derives an array from when it updates (a bitmap's texels -> the
    texture that lookups read) reaches it through an edge outside the render's isolate_grad
    scope, which a vertex's push crossed and cleared, so later vertices reached nothing (a
    textured area emitter: forward 12.26 against stock's 16.19; test_prb.py's textured test).
    Each vertex's own edges are new, so nothing is pushed twice."""
    if dr.flag(dr.JitFlag.VCallRecord) and not dr.grad_enabled(Lo):
        raise ValueError("the contribution of a replayed path is attached to no scene parameter: call "
                         "dr.enable_grad on the parameter (and params.update()) before differentiating")
    if mode == dr.ADMode.Backward:
        dr.backward_from(dr.select(active, dL * Lo, 0),
                         flags=dr.ADFlag.Default if megakernel else dr.ADFlag.ClearVertices)
        return dL
    flags = dr.ADFlag.Default if megakernel else dr.ADFlag.ClearEdges
    return dr.select(active, dL + dr.forward_to(Lo, flags=flags), dL)
