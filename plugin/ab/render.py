"""Choosing the variant, loading a scene, reading its path settings, rendering in passes, writing EXR: what the CLI, converge, the tests and the tools share."""
from __future__ import annotations

import contextlib
import math
import re
import resource
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from layerbvh_mitsuba.atomic import atomic_path
from layerbvh_mitsuba.runtime.compile_clock import CompileClock
from layerbvh_mitsuba.runtime.held_instances import instances_held
from layerbvh_mitsuba.runtime.registry import STANDS_IN_FOR

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

# Integrator objects by the names they give themselves, and their plugin names (for messages and
# reports). class_name() and to_string's prefix differ for some (volpath is VolumetricPathIntegrator
# and prints VolumetricSimplePathIntegrator[...]; volpathmis VolpathMisIntegratorImpl and
# VolumetricMisPathIntegrator[...]); a wrapper prints the integrators it holds by the latter.
INTEGRATOR_PLUGINS = {
    "PathIntegrator": "path",
    "VolumetricPathIntegrator": "volpath", "VolumetricSimplePathIntegrator": "volpath",
    "VolpathMisIntegratorImpl": "volpathmis", "VolumetricMisPathIntegrator": "volpathmis",
    "DirectIntegrator": "direct", "AOVIntegrator": "aov", "MomentIntegrator": "moment",
    "ParticleTracerIntegrator": "ptracer", "DepthIntegrator": "depth", "StokesIntegrator": "stokes",
    "PRBIntegrator": "prb", "LayerBVHIntegrator": "layerbvh",
}
WRAPPERS = ("aov", "moment", "stokes")  # integrators that run others and add channels
ESTIMATORS = tuple(STANDS_IN_FOR)  # Mitsuba's integrators ours mirror: path, direct, volpath, volpathmis


def _plugin(cls: str) -> str:
    return INTEGRATOR_PLUGINS.get(cls, cls.removesuffix("Integrator").lower())


def _items(text: str) -> list[str]:
    """The top-level items of the first `integrators = [...]` list in a wrapper's to_string."""
    start = text.find("integrators = [")
    if start < 0:
        return []
    items, depth, item = [], 0, ""
    for ch in text[start + len("integrators = ["):]:
        if ch == "[":
            depth += 1
        elif ch == "]":
            if depth == 0:
                break
            depth -= 1
        if ch == "," and depth == 0:
            items.append(item)
            item = ""
        else:
            item += ch
    return [i.strip() for i in items + [item] if i.strip()]


def _described(name: str, text: str) -> str:
    if name not in WRAPPERS:
        return name
    inner = [_described(_plugin(i.split("[", 1)[0].strip()), i) for i in _items(text)]
    return f"{name}({', '.join(inner)})" if inner else name


def integrator_name(integ) -> str:
    """The plugin name of a Mitsuba integrator object (`path`, `volpath`, `prb`, ...); a wrapper
    is named with what it wraps: `moment(volpath)`, `aov(direct)`, `moment(path, volpath)`."""
    cls = integ.class_name()
    if cls not in INTEGRATOR_PLUGINS:  # Python integrators (prb, ...) report their base class
        cls = str(integ).split("[", 1)[0].strip() or cls
    return _described(_plugin(cls), str(integ))


def inner_integrator_text(integ) -> str:
    """The to_string of the first integrator a wrapper runs (of the integrator itself if it
    wraps none): where its max_depth and rr_depth are read."""
    items = _items(str(integ)) if _plugin(integ.class_name()) in WRAPPERS else []
    return items[0] if items else str(integ)


def _int_setting(text: str, key: str) -> int | None:
    m = re.search(rf"\b{key}\s*=\s*(-?\d+)", text)
    return signed_depth(int(m.group(1))) if m else None


@dataclass(frozen=True)
class Wrapper:
    """An `aov` or `moment` integrator around one of ESTIMATORS (possibly through another such
    wrapper), as the scene's XML states it: it adds channels (AOVs, second moments) to the
    estimator's result and changes nothing else. `wrap(inner)` is the same wrapper around another
    integrator (a dict or a loaded object): stock's estimator, or ours standing in for it."""

    type: str                        # "aov" | "moment"
    props: tuple = ()                # its own properties as (name, value) pairs (aov: aovs)
    inner: "Wrapper | None" = None   # a wrapper it wraps, else it wraps the estimator itself
    leaf: str = "path"               # the estimator inside: one of ESTIMATORS

    def wrap(self, inner) -> dict:
        return {"type": self.type, **dict(self.props), "inner": inner if self.inner is None else self.inner.wrap(inner)}

    @property
    def name(self) -> str:
        return f"{self.type}({self.leaf if self.inner is None else self.inner.name})"


def substituted(value: str | None, defaults: dict) -> str | None:
    """A scene file's attribute with its `$name` parameters replaced by their values (`defaults`)."""
    return None if value is None else re.sub(r"\$(\w+)", lambda m: str(defaults.get(m.group(1), m.group(0))), value)


def _xml_booleans(el, defaults: dict) -> dict:
    """An <integrator> element's boolean properties, by name, as written ("true"/"false")."""
    return {c.get("name"): substituted(c.get("value"), defaults) for c in el if c.tag == "boolean"}


def _xml_wrapper(el, defaults: dict) -> tuple[Wrapper | None, dict]:
    """(the wrapper, the inner estimator's XML boolean properties) of an <integrator> element, or
    (None, {}) when it is not aov/moment around exactly one of ESTIMATORS with properties we know."""
    kind = substituted(el.get("type"), defaults)
    if kind not in ("aov", "moment"):
        return None, {}
    props, inner = [], []
    for child in el:
        if child.tag == "integrator":
            inner.append(child)
        elif kind == "aov" and child.tag == "string" and child.get("name") == "aovs":
            props.append(("aovs", substituted(child.get("value"), defaults)))
        elif child.tag != "default":
            return None, {}
    if len(inner) != 1:
        return None, {}
    leaf = substituted(inner[0].get("type"), defaults)
    if leaf in ESTIMATORS:
        return Wrapper(kind, tuple(props), leaf=leaf), _xml_booleans(inner[0], defaults)
    nested, path = _xml_wrapper(inner[0], defaults)
    return (None, {}) if nested is None else (Wrapper(kind, tuple(props), nested, leaf=nested.leaf), path)


def referenced_file(name: str, including: Path, scene_dir: Path) -> Path | None:
    """Where Mitsuba finds a relative file name written in `including` (the scene file or a file
    it <include>s): next to that file, else in the scene file's folder, which Mitsuba's file
    resolver holds (Mitsuba's own test scenes include `include/preamble.xml` from a file in
    include/); None if neither holds it."""
    return next((c for c in ((including.parent / name).resolve(), (scene_dir / name).resolve()) if c.is_file()), None)


def _scene_integrator(path: Path, defaults: dict, seen: set, scene_dir: Path | None = None):
    """The first <integrator> of a scene file in document order, <include>d files read where they
    stand (as Mitsuba merges them); None if there is none or a file cannot be read."""
    path = path.resolve()
    if path in seen:
        return None
    seen.add(path)
    scene_dir = scene_dir or path.parent
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return None
    for d in root.iter("default"):
        defaults.setdefault(d.get("name"), d.get("value"))
    for el in root:
        if el.tag == "integrator":
            return el
        if el.tag == "include" and el.get("filename"):
            included = referenced_file(substituted(el.get("filename"), defaults), path, scene_dir)
            found = None if included is None else _scene_integrator(included, defaults, seen, scene_dir)
            if found is not None:
                return found
    return None


def scene_wrapper(scene_path, params: dict | None = None) -> tuple[Wrapper | None, dict]:
    """The wrapper around one of ESTIMATORS that the scene file's <integrator> states, read from
    its XML (an `aov` wrapper's channel list is in its properties, not in the loaded object;
    <include>d files are followed), and the inner estimator's boolean properties; (None, the
    estimator's boolean properties) for an estimator without a wrapper (volpathmis's
    use_spectral_mis is not in the loaded object); (None, {}) for anything else."""
    defaults = {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in (params or {}).items()}
    el = _scene_integrator(Path(scene_path), defaults, set())
    if el is not None and substituted(el.get("type"), defaults) in ESTIMATORS:
        return None, _xml_booleans(el, defaults)
    return (None, {}) if el is None else _xml_wrapper(el, defaults)


@dataclass
class PathSettings:
    """The settings both sides of a comparison render with, and where they come from.

    `estimator`: the scene's estimator, `path`, `direct`, `volpath` or `volpathmis` (ours stands
    in for it: runtime.registry.STANDS_IN_FOR). `props`: its settings (path, volpath: max_depth,
    rr_depth, hide_emitters; volpathmis: those and use_spectral_mis; direct: emitter_samples,
    bsdf_samples, hide_emitters; only those the scene sets). `scene_integrator`: the scene's
    integrator (`integrator_name`). `wrapper`: the scene's `aov`/`moment` around its estimator, kept on both sides (stock's estimator inside on one, ours on the other).
    `as_path`: the scene's integrator is neither path nor such a wrapper and the user asked to
    compare it as path (`--as-path`); `note` says what was taken from it."""

    props: dict
    scene_integrator: str
    as_path: bool = False
    note: str = ""
    wrapper: Wrapper | None = None
    estimator: str = "path"

    def stock_inner(self) -> dict:
        """Stock's estimator (inside the wrapper, where there is one)."""
        return {"type": self.estimator, **self.props}

    @property
    def ours_type(self) -> str:
        """The plugin of ours that stands in for the scene's estimator."""
        return STANDS_IN_FOR[self.estimator]

    def integrator(self, inner):
        """What a side renders: `inner` (stock's estimator or ours, a dict or a loaded object), in
        the scene's wrapper where it has one."""
        return inner if self.wrapper is None else self.wrapper.wrap(inner)

    @property
    def compared_as(self) -> str:
        if self.wrapper:
            return self.wrapper.name
        return self.estimator + (" (--as-path)" if self.as_path else "")


SUPPORTED = "path, direct, volpath, volpathmis, and aov or moment around them"


def path_settings(mi, scene, as_path: bool = False, scene_path=None, params: dict | None = None) -> PathSettings:
    """The scene's own estimator and its settings, read from its integrator object: `path`
    (max_depth, rr_depth, hide_emitters) or `direct` (emitter_samples, bsdf_samples,
    hide_emitters), and an `aov`/`moment` wrapper around either (read from `scene_path`'s XML with
    its `params`), kept as `wrapper`. Any other integrator is refused (UserError) unless
    `as_path`: then it is compared as path, its settings read where it has them (a wrapper's inner
    integrator, volpath's depths)."""
    integ = scene.integrator()
    if integ is None:
        return PathSettings({}, "path")
    name = integrator_name(integ)
    wrapper, inner_xml = scene_wrapper(scene_path, params) if scene_path is not None else (None, {})
    if wrapper is not None and wrapper.name != name:
        wrapper = None  # the XML's first <integrator> is not the one loaded (an include): not read
    own = name in ESTIMATORS
    if not own and wrapper is None and not as_path:
        raise UserError(f"the scene's integrator is {name}: layerbvh renders {SUPPORTED}, so both sides would "
                        f"render something else than the scene asks; pass --as-path to compare them rendered with "
                        f"path")
    estimator = name if own else wrapper.leaf if wrapper is not None else "path"
    inner = inner_integrator_text(integ)
    keys = ("emitter_samples", "bsdf_samples") if estimator == "direct" else ("max_depth", "rr_depth")
    props = {k: v for k in keys if (v := _int_setting(inner, k)) is not None}
    if own or name == "volpath":
        props["hide_emitters"] = bool(integ.hide_emitters)
    elif wrapper is not None and "hide_emitters" in inner_xml:
        props["hide_emitters"] = inner_xml["hide_emitters"].lower() == "true"
    if estimator == "volpathmis" and "use_spectral_mis" in inner_xml:  # (only the XML has it)
        props["use_spectral_mis"] = inner_xml["use_spectral_mis"].lower() == "true"
    note = ""
    if not own and wrapper is None:
        shown = ", ".join(f"{k}={v}" for k, v in props.items()) or "path's defaults"
        note = f"the scene's integrator is {name}; both sides rendered with path ({shown})"
    return PathSettings(props, name, as_path=not own and wrapper is None, note=note, wrapper=wrapper,
                        estimator=estimator)


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
                with instances_held():  # (stock's too: another thread, a progress bar's, may collect meanwhile)
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


def timed_render(mi, scene, integrator, spp: int, seed: int, label: str = "", progress: bool = False,
                 calibrated=None) -> TimedRender:
    """`render_passes`, with kernel compilation and auto calibration taken out of the render time.

    Dr.Jit compiles a kernel the first time it sees it; a render that meets a new one pays for
    the compile inside its wall time. Dr.Jit's kernel history reports each launch's compile
    time (zero for kernels found in its on-disk cache), so it is reported on its own. Auto's
    calibration is read from `calibrated` (default: the integrator itself; a wrapper's inner
    layerbvh where a wrapper renders)."""
    calibration = getattr(calibrated if calibrated is not None else integrator, "calibration_s", lambda: 0.0)
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
