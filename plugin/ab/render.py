"""Choosing the variant, loading a scene, reading its path settings, rendering in passes, writing EXR: what the CLI, converge, the tests and the tools share."""
from __future__ import annotations

import contextlib
import math
import re
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from layerbvh_mitsuba.atomic import atomic_path
from layerbvh_mitsuba.runtime.compile_clock import CompileClock

DEFAULT_VARIANT = "llvm_ad_rgb"  # Embree on the CPU, the same threads as our LLVM backend
SPP_PER_PASS = 64  # a progress bar step; one pass (the exact seed) whenever spp <= this
MAX_RAYS_PER_PASS = 1 << 24  # and at most this many camera rays per pass (512x512 at 64 spp)


class UserError(Exception):
    """Bad input (a scene, an option, a variant), reported to the user as one line."""


def use_variant(variant: str | None = None):
    """Mitsuba with `variant` active (default: the active one, else DEFAULT_VARIANT), and the
    `layerbvh` integrator registered for it. Our traversal runs on Dr.Jit's JIT backends, so
    scalar variants are refused, and CUDA ones where no CUDA device is usable."""
    want = variant or mi.variant() or DEFAULT_VARIANT
    if want not in mi.variants():
        raise UserError(f"Mitsuba variant {want!r} is not available (choose one of {', '.join(mi.variants())})")
    if not want.startswith(("llvm_", "cuda_")):
        raise UserError(f"variant {want!r} is a scalar variant: layerbvh traces on Dr.Jit's JIT backends; choose an "
                        f"llvm_* or cuda_* variant")
    if want.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        raise UserError(f"variant {want!r} needs a CUDA device and none is usable here; choose an llvm_* variant")
    if mi.variant() != want:
        mi.set_variant(want)
    return mi


def pass_seed(seed: int, k: int, passes: int) -> int:
    """Seed of pass k of `passes`: the user's seed itself when there is one pass, else one far
    from any other seed's passes (7919 is prime, so seeds s and s' never share a pass seed for
    k < 7919)."""
    return seed if passes == 1 else seed * 7919 + k


@contextlib.contextmanager
def _exr_threads():
    """Mitsuba's EXR reader and writer never return when Dr.Jit runs one thread (a process
    limited to one CPU: `taskset -c 0`, a one-CPU container): they run with two."""
    threads = dr.thread_count()
    if threads < 2:
        dr.set_thread_count(2)
    try:
        yield
    finally:
        if threads < 2:
            dr.set_thread_count(threads)


def write_exr(path, img: np.ndarray) -> None:
    """Write a linear float32 image as EXR, whole or not at all (temporary sibling, then rename)."""
    mi = use_variant()
    with _exr_threads(), atomic_path(path) as tmp:
        mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32)).write(tmp)


def read_exr(path) -> np.ndarray:
    """An EXR (or any image Mitsuba reads) as a float32 array, its channels as stored."""
    mi = use_variant()
    with _exr_threads():
        return np.array(mi.Bitmap(str(path)), np.float32)


def load_scene(mi, path: str, res=None, **params):
    """Load an XML scene (with optional $parameters); `res` overrides the film of its first
    sensor, whether or not the scene declares resolution parameters."""
    try:
        with _exr_threads():  # an EXR texture or environment map is read while loading
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


def load_integrator(mi, props: dict):
    """`mi.load_dict(props)` for an integrator; a bad property is a UserError with Mitsuba's (or
    our integrator's) last line."""
    try:
        return mi.load_dict(props)
    except Exception as e:  # Mitsuba wraps a plugin constructor's error in a multi-line RuntimeError
        raise UserError(f"integrator {props.get('type')}: {str(e).strip().splitlines()[-1]}") from None


def signed_depth(value: int) -> int:
    """Mitsuba keeps max_depth as uint32, so -1 (infinite) reads back as 2^32 - 1: map it back."""
    return value - 2 ** 32 if value >= 2 ** 31 else value


# -- what the scene's integrator asks for -------------------------------------------------------------

# Mitsuba class names of integrators and their plugin names (for messages and reports).
INTEGRATOR_PLUGINS = {
    "PathIntegrator": "path", "VolumetricPathIntegrator": "volpath", "VolumetricMISPathIntegrator": "volpathmis",
    "DirectIntegrator": "direct", "AOVIntegrator": "aov", "MomentIntegrator": "moment",
    "ParticleTracerIntegrator": "ptracer", "DepthIntegrator": "depth", "StokesIntegrator": "stokes",
}


def integrator_name(integ) -> str:
    """The plugin name of a Mitsuba integrator object (`path`, `volpath`, `prb`, ...); wrappers
    around a path tracer read `moment(path)`."""
    cls = integ.class_name()
    if cls not in INTEGRATOR_PLUGINS:  # Python integrators (prb, ...) report their base class
        cls = str(integ).split("[", 1)[0].strip() or cls
    name = INTEGRATOR_PLUGINS.get(cls, cls.removesuffix("Integrator").lower())
    if name in ("moment", "aov") and "PathIntegrator[" in str(integ):
        name += "(path)"
    return name


def _int_setting(text: str, key: str) -> int | None:
    m = re.search(rf"\b{key}\s*=\s*(-?\d+)", text)
    return signed_depth(int(m.group(1))) if m else None


@dataclass
class PathSettings:
    """The `path` settings both sides of a comparison render with, and where they come from.

    `props`: max_depth, rr_depth, hide_emitters (only those the scene sets). `scene_integrator`:
    the scene's integrator (`integrator_name`). `as_path`: the scene's integrator is not `path`
    and the user asked to compare it as one (`--as-path`); `note` says what was taken from it."""

    props: dict
    scene_integrator: str
    as_path: bool = False
    note: str = ""


def path_settings(mi, scene, as_path: bool = False) -> PathSettings:
    """The scene's own path settings (max_depth, rr_depth, hide_emitters, read from its integrator
    object). A scene whose integrator is not `path` is refused (UserError) unless `as_path`:
    then its settings are read where it has them (a wrapper's inner path, volpath's depths)."""
    integ = scene.integrator()
    if integ is None:
        return PathSettings({}, "path")
    name = integrator_name(integ)
    text = str(integ)
    if name != "path" and not as_path:
        raise UserError(f"the scene's integrator is {name}, not path: layerbvh renders with a path tracer, so "
                        f"both sides would render something else than the scene asks; pass --as-path to compare "
                        f"them rendered with path")
    inner = text[text.index("PathIntegrator["):] if name != "path" and "PathIntegrator[" in text else text
    props = {k: v for k in ("max_depth", "rr_depth") if (v := _int_setting(inner, k)) is not None}
    if name == "path" or name == "volpath":
        props["hide_emitters"] = bool(integ.hide_emitters)
    note = ""
    if name != "path":
        shown = ", ".join(f"{k}={v}" for k, v in props.items()) or "path's defaults"
        note = f"the scene's integrator is {name}; both sides rendered with path ({shown})"
    return PathSettings(props, name, as_path=name != "path", note=note)


def path_props(mi, scene) -> dict:
    """The scene's path settings, comparing any integrator as path (tools that say so themselves)."""
    return path_settings(mi, scene, as_path=True).props


def passes_for(pixels: int, spp: int) -> tuple[int, int]:
    """(passes, spp per pass) for `spp` samples of a `pixels`-pixel film: passes of at most
    SPP_PER_PASS spp and MAX_RAYS_PER_PASS rays (camera rays of one pass are traced together, so
    the pass size bounds the render's memory); one pass whenever spp fits."""
    per_pass = max(1, min(SPP_PER_PASS, MAX_RAYS_PER_PASS // max(pixels, 1)))
    return max(1, math.ceil(spp / per_pass)), per_pass


def _check_interrupt(integrator, error: BaseException | None = None) -> None:
    """Raise KeyboardInterrupt if Ctrl-C reached the last render. Mitsuba catches SIGINT during a
    render, cancels it (the integrator's `should_stop()` is then True) and passes the signal on to
    Python, whose KeyboardInterrupt may surface wrapped in a RuntimeError (dr.custom)."""
    cause = error
    while cause is not None:
        if isinstance(cause, KeyboardInterrupt):
            raise KeyboardInterrupt from None
        cause = cause.__cause__ or cause.__context__
    if getattr(integrator, "should_stop", lambda: False)():
        raise KeyboardInterrupt


def render_passes(mi, scene, integrator, spp: int, seed: int, label: str, progress: bool):
    """Render in passes (`passes_for`) with a progress bar; a single pass uses `seed` itself.
    Ctrl-C stops it after the pass it arrives in (KeyboardInterrupt): no partial image."""
    size = scene.sensors()[0].film().crop_size()
    passes, per_pass = passes_for(int(size[0]) * int(size[1]), spp)
    acc, done = None, 0
    t0 = time.perf_counter()
    with tqdm(total=spp, desc=label, unit="spp", disable=not progress, leave=False, file=sys.stderr) as bar:
        for k in range(passes):
            n = min(per_pass, spp - done)
            try:
                img = mi.render(scene, integrator=integrator, spp=n, seed=pass_seed(seed, k, passes))
                dr.eval(img)
            except RuntimeError as e:
                _check_interrupt(integrator, e)
                raise
            _check_interrupt(integrator)
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
    calibration = getattr(integrator, "calibration_s", lambda: 0.0)
    cal0 = calibration()
    with CompileClock() as clock:
        img, wall = render_passes(mi, scene, integrator, spp, seed, label, progress)
    compile_s = clock.seconds
    cal = calibration() - cal0
    return TimedRender(img, wall, max(wall - compile_s - cal, 0.0), compile_s, cal)


# -- memory ------------------------------------------------------------------------------------------

# Bytes per film pixel (the film's channels, the developed image and the copies a render makes)
# and per camera ray of a pass (sampler state, sample positions and weights, path state, queries).
# Estimates, rounded up from what a render allocates (Mitsuba's block and ours); see memory_estimate.
FILM_BYTES_PER_PIXEL = 96
RAY_BYTES = {"megakernel": 160, "wavefront": 1024}
MAX_LANES = 1 << 32  # Dr.Jit arrays hold fewer than 2^32 entries


def available_memory() -> int | None:
    """Bytes this process can still allocate: the least of the system's MemAvailable, the
    cgroup's limit less its usage (containers) and the address-space limit (`ulimit -v`) less
    this process's size; None where none can be read."""
    limits = []
    try:
        with open("/proc/meminfo") as fh:
            limits += [int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("MemAvailable:")]
    except OSError:
        pass
    try:
        cap = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if cap != "max":
            limits.append(int(cap) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        try:
            with open("/proc/self/status") as fh:
                size = next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmSize:"))
            limits.append(soft - size)
        except (OSError, StopIteration):
            limits.append(soft)
    return max(min(limits), 0) if limits else None


def memory_estimate(width: int, height: int, spp: int, loop: str, work_bytes: int = 0) -> dict:
    """What a render of width x height at `spp` needs, in bytes: the film, one pass's rays
    (`passes_for`) in the given loop ("megakernel" or "wavefront"), and the traversal's BVH and
    work memory (`work_bytes`)."""
    pixels = width * height
    passes, per_pass = passes_for(pixels, spp)
    rays = pixels * min(per_pass, spp)
    film = pixels * FILM_BYTES_PER_PIXEL
    per_pass_bytes = rays * RAY_BYTES[loop]
    return {"pixels": pixels, "rays_per_pass": rays, "passes": passes, "film": film, "rays": per_pass_bytes,
            "traversal": work_bytes, "total": film + per_pass_bytes + work_bytes}


def check_memory(width: int, height: int, spp: int, loop: str = "wavefront", work_bytes: int = 0,
                 what: str = "the render") -> dict:
    """The estimate, or a UserError (one line) when it exceeds the available memory or what one
    Dr.Jit array can index."""
    e = memory_estimate(width, height, spp, loop, work_bytes)
    gib = (lambda b: f"{b / 2 ** 30:.1f} GiB")
    if e["rays_per_pass"] >= MAX_LANES:
        raise UserError(f"{what} at {width}x{height} traces {e['rays_per_pass']:,} camera rays in one pass, more "
                        f"than Dr.Jit arrays can hold ({MAX_LANES:,}); lower the resolution")
    free = available_memory()
    if free is not None and e["total"] > free:
        raise UserError(f"{what} at {width}x{height}, {spp} spp needs about {gib(e['total'])} (film "
                        f"{gib(e['film'])}, one pass of {e['rays_per_pass']:,} rays {gib(e['rays'])}, traversal "
                        f"{gib(e['traversal'])}); {gib(free)} is available: lower --res or --spp")
    return e
