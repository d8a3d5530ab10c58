"""Choosing the variant, loading a scene, reading its path settings, rendering in passes, writing EXR: what the CLI, converge, the tests and the tools share."""
from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path

DEFAULT_VARIANT = "llvm_ad_rgb"  # Embree on the CPU, the same threads as our LLVM backend
SPP_PER_PASS = 64  # a progress bar step; one pass (the exact seed) whenever spp <= this


class UserError(Exception):
    """Bad input (a scene, an option, a variant), reported to the user as one line."""


def use_variant(variant: str | None = None):
    """Mitsuba with `variant` active (default: the active one, else DEFAULT_VARIANT), and the
    `layerbvh` integrator registered for it."""
    import mitsuba as mi
    want = variant or mi.variant() or DEFAULT_VARIANT
    if mi.variant() != want:
        try:
            mi.set_variant(want)
        except Exception:
            raise UserError(f"Mitsuba variant {want!r} is not available (choose one of "
                            f"{', '.join(mi.variants())})") from None
    import layerbvh_mitsuba  # noqa: F401  (registers the integrator, also for later variants)
    return mi


def pass_seed(seed: int, k: int, passes: int) -> int:
    """Seed of pass k of `passes`: the user's seed itself when there is one pass, else one far
    from any other seed's passes (7919 is prime, so seeds s and s' never share a pass seed for
    k < 7919)."""
    return seed if passes == 1 else seed * 7919 + k


def write_exr(path, img: np.ndarray) -> None:
    """Write a linear float32 image as EXR, whole or not at all (temporary sibling, then rename)."""
    mi = use_variant()
    with atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)).write(tmp)


def load_scene(mi, path: str, res=None, **params):
    """Load an XML scene (with optional $parameters); `res` overrides the film of its first
    sensor, whether or not the scene declares resolution parameters."""
    try:
        scene = mi.load_file(str(path), **params)
    except Exception as e:  # Mitsuba raises RuntimeError with a multi-line message
        raise UserError(f"cannot load scene {path}: {str(e).strip().splitlines()[-1]}") from None
    if not scene.sensors():
        raise UserError(f"scene {path} has no sensor")
    if res is not None:
        params = mi.traverse(scene.sensors()[0])
        params["film.size"] = list(res)
        params["film.crop_size"] = list(res)
        params["film.crop_offset"] = [0, 0]
        params.update()
    return scene


def signed_depth(value: int) -> int:
    """Mitsuba keeps max_depth as uint32, so -1 (infinite) reads back as 2^32 - 1: map it back."""
    return value - 2 ** 32 if value >= 2 ** 31 else value


def path_props(mi, scene) -> dict:
    """The scene's own integrator settings when it is a `path` (else path's defaults)."""
    integ = scene.integrator()
    out = {}
    if integ is not None and integ.class_name() == "PathIntegrator":
        for key in ("max_depth", "rr_depth", "hide_emitters"):
            try:
                out[key] = mi.traverse(integ)[key]
            except Exception:
                pass
        # Not traversable in every version: read from the string form as a fallback.
        text = str(integ)
        for key in ("max_depth", "rr_depth"):
            if key not in out:
                for line in text.splitlines():
                    if line.strip().startswith(key):
                        out[key] = int(line.split("=")[1].strip().rstrip(","))
        for key in ("max_depth", "rr_depth"):
            if key in out:
                out[key] = signed_depth(int(out[key]))
    return out


def render_passes(mi, scene, integrator, spp: int, seed: int, label: str, progress: bool):
    """Render in passes of SPP_PER_PASS with a progress bar; a single pass uses `seed` itself."""
    import drjit as dr
    from tqdm import tqdm
    passes = max(1, math.ceil(spp / SPP_PER_PASS))
    acc, done = None, 0
    t0 = time.perf_counter()
    with tqdm(total=spp, desc=label, unit="spp", disable=not progress, leave=False, file=sys.stderr) as bar:
        for k in range(passes):
            n = min(SPP_PER_PASS, spp - done) if passes > 1 else spp
            img = mi.render(scene, integrator=integrator, spp=n, seed=pass_seed(seed, k, passes))
            dr.eval(img)
            part = np.array(img, np.float32) * n
            acc = part if acc is None else acc + part
            done += n
            bar.update(n)
    return acc / spp, time.perf_counter() - t0


def scene_spp(scene) -> int:
    return scene.sensors()[0].sampler().sample_count()


@dataclass
class TimedRender:
    """A render and where its wall time went."""

    image: np.ndarray
    wall_s: float         # everything
    seconds: float        # the render itself: wall time less compilation and calibration
    compile_s: float      # Dr.Jit kernels compiled during it (LLVM/NVRTC, from the kernel history)
    calibration_s: float  # auto's timing runs (layerbvh integrator)


def timed_render(mi, scene, integrator, spp: int, seed: int, label: str = "", progress: bool = False) -> TimedRender:
    """`render_passes`, with kernel compilation and auto calibration taken out of the render time.

    Dr.Jit compiles a kernel the first time it sees it; a render that meets a new one pays for
    the compile inside its wall time. Dr.Jit's kernel history reports each launch's compile
    time (zero for kernels found in its on-disk cache), so it is reported on its own."""
    import drjit as dr
    calibration = getattr(integrator, "calibration_s", lambda: 0.0)
    cal0 = calibration()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()  # drop what came before
    try:
        img, wall = render_passes(mi, scene, integrator, spp, seed, label, progress)
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    compile_s = sum(k.get("backend_time", 0.0) + k.get("codegen_time", 0.0)
                    for k in history if not k.get("cache_hit")) / 1e3  # ms
    cal = calibration() - cal0
    return TimedRender(img, wall, max(wall - compile_s - cal, 0.0), compile_s, cal)


def cache_dir(kind: str) -> Path:
    """$XDG_CACHE_HOME/layerbvh/<kind> (default ~/.cache/layerbvh/<kind>): stock references,
    auto's decisions."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "layerbvh" / kind
