"""The order in which stock's wheel draws the two numbers of a `bsdf->sample(...,
sampler->next_1d(), sampler->next_2d())` call, probed from stock itself once per wheel, and the one
helper every mirror of such a call draws through.

C++ leaves the evaluation order of a call's arguments to the compiler. Mitsuba's wheels are built
with GCC, which evaluates them right to left: the 2D sample is drawn before the 1D one, in
`direct`'s BSDF sample, in `ptracer`'s, and in volpath's BSDF and phase samples. A same-seed
render follows stock draw for draw only in that order (measured: the other order gives other
BSDF samples). A wheel built by another compiler may draw them left to right, and a hard-coded
order would then break every same-seed comparison of those estimators silently (issue 55).

The probe (`_probe`, run in a subprocess: it needs the scalar_rgb variant, and switching variants
inside a running render is not safe) renders one pixel with stock `direct` over a sphere whose
BSDF is ours in Python, with a sampler that numbers its draws: the BSDF sees which draw each of
its two numbers came from. The answer is kept on disk per wheel (`cache_dir("draw_order")`,
keyed by Mitsuba's version and its library's path, size and time), so a machine probes once.
The helpers that draw in stock's integrators' own Python order (prb, prbvolpath: Python
evaluates left to right) do not go through here.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import mitsuba as mi

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.runtime.cache import cache_dir

_answer: bool | None = None  # this process's: the 2D sample first


def _wheel_key() -> str:
    """Mitsuba's version and its core library's path, size and modification time."""
    folder = Path(mi.__file__).parent
    libs = sorted(folder.glob("libmitsuba*")) or [Path(mi.__file__)]
    stat = libs[0].stat()
    text = f"{getattr(mi, '__version__', '?')}|{libs[0].resolve()}|{stat.st_size}|{stat.st_mtime_ns}"
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def bsdf_2d_first() -> bool:
    """True where stock's wheel draws a BSDF sample's 2D number before its 1D one (GCC's build)."""
    global _answer
    if _answer is None:
        path = cache_dir("draw_order") / f"{_wheel_key()}.json"
        try:
            _answer = bool(json.loads(path.read_text())["bsdf_2d_first"])
        except (OSError, ValueError, KeyError):
            out = subprocess.run([sys.executable, "-m", "layerbvh_mitsuba.runtime.draw_order"], capture_output=True,
                                 text=True, timeout=300, env={**os.environ, "PYTHONWARNINGS": "ignore"})
            if out.returncode != 0:
                raise RuntimeError(f"the probe of stock's draw order failed: {out.stderr.strip()[-300:]}")
            _answer = bool(json.loads(out.stdout.strip().splitlines()[-1])["bsdf_2d_first"])
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic.write_text(path, json.dumps({"bsdf_2d_first": _answer}))
    return _answer


def draws(sampler, active):
    """(sample1, sample2) of a mirrored `bsdf->sample` or `phase->sample` call: the 1D and 2D
    numbers drawn from `sampler` in stock's order (`bsdf_2d_first`)."""
    if bsdf_2d_first():
        sample2 = sampler.next_2d(active)
        return sampler.next_1d(active), sample2
    sample1 = sampler.next_1d(active)
    return sample1, sampler.next_2d(active)


def _probe() -> bool:
    """Render one pixel with stock `direct` in scalar_rgb: which draw reached the BSDF's sample1
    and which its sample2 (see the module docstring)."""
    mi.set_variant("scalar_rgb")
    seen: dict = {}
    count = [0]

    class Numbered(mi.Sampler):
        """Draw k returns k / 1000 (the 2D draw in both coordinates)."""

        def next_1d(self, active=True):
            count[0] += 1
            return count[0] / 1000.0

        def next_2d(self, active=True):
            count[0] += 1
            return mi.Point2f(count[0] / 1000.0, 0.5)

        def seed(self, seed, wavefront_size=1):
            count[0] = 0

        def fork(self):
            return Numbered(mi.Properties())

        def clone(self):
            return Numbered(mi.Properties())

        def to_string(self):
            return "Numbered"

    class Witness(mi.BSDF):
        """A diffuse BSDF that keeps the numbers its `sample` was given."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [self.m_flags]

        def sample(self, ctx, si, sample1, sample2, active=True):
            seen.setdefault("draws", (round(sample1 * 1000), round(sample2[0] * 1000)))
            bs = mi.BSDFSample3f()
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
            bs.eta, bs.sampled_type, bs.sampled_component = 1.0, int(mi.BSDFFlags.DiffuseReflection), 0
            return bs, mi.Color3f(0.5)

        def eval(self, ctx, si, wo, active=True):
            return mi.Color3f(0.1)

        def pdf(self, ctx, si, wo, active=True):
            return 0.3

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Color3f(0.1), 0.3

        def to_string(self):
            return "Witness"

    mi.register_sampler("layerbvh_numbered", lambda props: Numbered(props))
    mi.register_bsdf("layerbvh_witness", lambda props: Witness(props))
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 1, "height": 1},
                   "sampler": {"type": "layerbvh_numbered", "sample_count": 1}},
        "sphere": {"type": "sphere", "radius": 3.0, "bsdf": {"type": "layerbvh_witness"}},
        "light": {"type": "constant"}})
    mi.render(scene, spp=1)
    if "draws" not in seen:
        raise RuntimeError("stock direct never sampled the probe's BSDF")
    one, two = seen["draws"]
    return two < one


if __name__ == "__main__":
    print(json.dumps({"bsdf_2d_first": _probe()}))
