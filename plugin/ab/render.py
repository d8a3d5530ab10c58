"""Choosing the variant, loading a scene, rendering in passes (timed, interruptible), writing EXR: what the CLI,
converge, the tests and the tools share."""
from __future__ import annotations

import contextlib
import math
import re
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
from layerbvh_mitsuba.runtime.held_instances import instances_held

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


SEED_MAX = (1 << 32) - 1  # Mitsuba's sampler seed is a 32-bit unsigned integer (mi.render's `seed`)


SPP_MAX = (1 << 32) - 1  # ... and its sample count one too (a sampler's sample_count)


def check_spp(spp: int | None, option: str = "--spp") -> None:
    """Refuse (UserError, one line) a sample count below 1, or one Mitsuba's sampler cannot hold
    (10^14 was taken and rendered for ever: issue 56)."""
    if spp is not None and not 1 <= spp <= SPP_MAX:
        raise UserError(f"{option} must be from 1 to {SPP_MAX} (Mitsuba's sample count is 32-bit), got {spp}")


def check_seed(seed: int, option: str = "--seed") -> None:
    """Refuse (UserError, one line) a seed Mitsuba's sampler cannot take."""
    if not 0 <= seed <= SEED_MAX:
        raise UserError(f"{option} must be from 0 to {SEED_MAX} (Mitsuba's sampler seed is 32-bit), got {seed}")


def pass_seed(seed: int, k: int, passes: int) -> int:
    """Seed of pass k of `passes`: the user's seed itself when there is one pass, else
    seed x 7919 + k modulo 2^32 (within the sampler's 32 bits for every seed a user may give:
    issue 56, a Unix time as the seed overflowed). 7919 is odd, so for each k distinct seeds
    give distinct pass seeds, and seeds below 2^32 / 7919 never share a pass seed for k < 7919."""
    return seed if passes == 1 else (seed * 7919 + k) % (SEED_MAX + 1)


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


def write_exr(path, img: np.ndarray, channels: list[str] | None = None) -> None:
    """Write a linear float32 image as EXR, whole or not at all (temporary sibling, then rename),
    its channels named `channels` where given (else Mitsuba's defaults: R, G, B, or ch00, ...)."""
    mi = use_variant()
    img = np.ascontiguousarray(img, dtype=np.float32)
    with _exr_threads(), atomic_path(path) as tmp:
        (mi.Bitmap(img) if channels is None else mi.Bitmap(img, channel_names=list(channels))).write(tmp)


def render_channels(integrator, count: int) -> list[str] | None:
    """The names of a render's `count` channels, as stock's film names them: the colour (Y; R, G,
    B; R, G, B, A) and then the integrator's AOVs (an aov wrapper's, stokes's S0.R ... S3.B);
    None where the count does not add up."""
    aovs = list(integrator.aov_names())
    colour = {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}.get(count - len(aovs))
    return None if colour is None else colour + aovs


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
        line = str(e).strip().splitlines()[-1]
        named = _file_behind(str(e))
        if named:
            line += f" ({named})"
        if "only be used in polarized mode" in line:  # (Mitsuba's stokes integrator)
            line += f" (the active variant is {mi.variant()}: pass --variant llvm_ad_spectral_polarized or " \
                    f"llvm_ad_mono_polarized)"
        raise UserError(f"cannot load scene {path}: {line}") from None
    if not scene.sensors():
        raise UserError(f"scene {path} has no sensor")
    if res is not None:
        params = mi.traverse(scene.sensors()[0])
        params["film.size"] = list(res)
        params["film.crop_size"] = list(res)
        params["film.crop_offset"] = [0, 0]
        params.update()
    size = list(scene.sensors()[0].film().crop_size())
    if min(size) < 1:  # (Mitsuba loads it, then fails inside mi.render: issue 56)
        raise UserError(f"scene {path}: its film is {size[0]}x{size[1]} pixels; give --res W H or a film "
                        f"width and height >= 1")
    return scene


LFS_POINTER = b"version https://git-lfs.github.com/spec/"  # how a Git LFS pointer file begins
_AT = re.compile(r"At (.+?) \(line (\d+), col (\d+)\)")
_FILENAME = re.compile(r'<string\b[^>]*\bname="filename"[^>]*>')  # (its value before or after the name)


def _file_behind(message: str) -> str:
    """The file a failed plugin was reading, named (Mitsuba's "Bitmap: Unknown file format!" names
    none, issue 56): the first `filename` at or after the XML position the message gives, and
    whether it is missing or a Git LFS pointer (a clone without `git lfs pull`). '' if none."""
    at = _AT.search(message)
    if not at or "Bitmap" not in message and "file" not in message.lower():
        return ""
    xml = Path(at.group(1))
    try:
        lines = xml.read_text(errors="replace").splitlines(keepends=True)
    except OSError:
        return ""
    line, col = int(at.group(2)), int(at.group(3))
    rest = "".join(lines[line - 1:])[max(col - 1, 0):]
    tag = _FILENAME.search(rest)
    value = re.search(r'\bvalue="([^"]*)"', tag.group(0)) if tag else None
    if not value:
        return ""
    name = value.group(1)
    file = Path(name) if Path(name).is_absolute() else xml.parent / name
    try:
        with open(file, "rb") as f:
            head = f.read(len(LFS_POINTER))
    except OSError:
        head = b""
    if head == LFS_POINTER:
        return f"{name} is a Git LFS pointer, not the file: fetch it with git lfs pull"
    return "" if name in message else f"reading {name}"


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
    """The scene's samples per pixel (its first sensor's sampler); refused where it is 0 (Mitsuba
    loads such a scene, and its render dies of a division by zero: issue 56)."""
    spp = scene.sensors()[0].sampler().sample_count()
    if spp < 1:
        raise UserError(f"the scene's sampler has sample_count {spp}; give --spp N or a sample_count >= 1")
    return spp


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


# Bytes per film pixel (the film's channels, the developed image and the copies a render makes)
# and per camera ray of a pass (sampler state, sample positions and weights, path state, queries).
