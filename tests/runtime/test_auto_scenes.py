"""auto on a multi-shape scene at its own depth: decided before the render (a pre-pass on the scene's rays), the
megakernel when every kind goes per_ray, decisions kept across processes under a key that does not depend on
Mitsuba's load order."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

import layerbvh
import layerbvh_mitsuba  # noqa: F401  (registers the integrator)
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab.scene_integrator import path_props

STAIRCASE = Path(__file__).resolve().parents[2] / "scenes" / "staircase2" / "scene.xml"  # 21 shapes, max_depth 65
RES, SPP = (48, 27), 4  # 5,184 rays per pass
# Below the CPU rule's 2^19 rays nothing would be timed; the pre-pass is what is tested here.
MIN_RAYS = 1024


def _auto(scene, margin=None, monkeypatch=None):
    integ = mi.load_dict({"type": "layerbvh", "traversal": "auto", **path_props(mi, scene)})
    integ.tracer(scene).bvh.auto.min_rays = MIN_RAYS
    if margin is not None:
        monkeypatch.setattr(layerbvh.auto, "AUTO_MARGIN", margin)
    return integ


def _render(scene, integ, seed=0):
    return np.array(mi.render(scene, integrator=integ, spp=SPP, seed=seed), np.float32)


@pytest.fixture(scope="module")
def staircase():
    scene = testing.load(STAIRCASE, RES)
    assert len(scene.shapes()) >= 20
    per_ray = mi.load_dict({"type": "layerbvh", "traversal": "per_ray", **path_props(mi, scene)})
    return scene, _render(scene, per_ray)


def test_per_ray_everywhere_renders_the_per_ray_megakernel(staircase, monkeypatch, tmp_path):
    """When the pre-pass settles every kind on per_ray, the render is per_ray's megakernel: the
    same image (the pre-pass has its own sampler, so the render's is untouched)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    scene, per_ray_img = staircase
    integ = _auto(scene, margin=0.99, monkeypatch=monkeypatch)  # sorting would need to be 100x faster
    img = _render(scene, integ)
    st = integ.last_stats
    n = RES[0] * RES[1] * SPP
    bounce = st.auto_choices[layerbvh.auto.choice_key(False, "bounce", n)]
    assert bounce["mode"] == "per_ray" and bounce["seconds"], bounce  # timed, by the pre-pass
    # Each kind is decided apart: camera and shadow rays by the CPU rule, untimed.
    for any_hit, hint in ((False, "camera"), (True, "shadow")):
        c = st.auto_choices[layerbvh.auto.choice_key(any_hit, hint, n)]
        assert c["seconds"] is None and "sorting never won" in c["reason"], c
    assert st.loop == "megakernel", st.loop
    assert st.calibration_s > 0
    # The same kernel and samples; the scene's tent filter splats samples with atomic adds,
    # whose order between threads moves the sums by float rounding (~1e-6), never more. A
    # pre-pass that drew from the render's sampler would change the image by ~0.1.
    assert np.abs(img - per_ray_img).max() <= 1e-5, np.abs(img - per_ray_img).max()


def test_sorting_wins_renders_the_wavefront_with_layer_sorted(staircase, monkeypatch, tmp_path):
    """When sorting wins the pre-pass, the render runs the wavefront loop with layer_sorted for
    the bounce rays, decided before it (nothing is timed during the render), and its image
    matches per_ray's up to float noise (every mode is exact)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    scene, per_ray_img = staircase
    integ = _auto(scene, margin=-100.0, monkeypatch=monkeypatch)  # layer_sorted always "faster"
    img = _render(scene, integ)
    st = integ.last_stats
    assert st.loop == "wavefront"
    assert st.modes_used.get("auto:layer_sorted", 0) >= 2, st.modes_used  # bounces at depth 1, 2, ...
    assert st.wavefront_steps > st.queries, "the layer path ran wavefront steps (per_ray: one per query)"
    d = np.abs(img - per_ray_img).max(-1)
    assert np.mean(d <= 1e-3) >= 0.99, f"{np.mean(d <= 1e-3)} of pixels within 1e-3"


CHILD = """
import json, sys
import mitsuba as mi
import layerbvh_mitsuba
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.ab.scene_integrator import path_props
scene = testing.load(sys.argv[1], (48, 27))
integ = mi.load_dict({"type": "layerbvh", "traversal": "auto", **path_props(mi, scene)})
tracer = integ.tracer(scene)
tracer.bvh.auto.min_rays = 1024
mi.render(scene, integrator=integ, spp=4, seed=0)
st = integ.last_stats
print(json.dumps({"key": tracer.device_key(), "loop": st.loop, "calibration_s": st.calibration_s,
                  "reasons": [c["reason"] for c in st.auto_choices.values()],
                  "order": [s.id() for s in scene.shapes()]}))
"""


def test_decisions_kept_across_processes_whatever_the_load_order(tmp_path, share_kernel_cache):
    """A first run times and keeps its decisions; a later run in another process (Mitsuba then
    loads the shapes in another order) finds them under the same key: nothing is timed, and
    the render is the megakernel whenever they all say per_ray."""
    env = {"XDG_CACHE_HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    share_kernel_cache(tmp_path)  # (our caches isolated, Dr.Jit's compiled kernels shared)

    def run():
        r = subprocess.run([sys.executable, "-c", CHILD, str(STAIRCASE)], capture_output=True, text=True,
                           timeout=300, env=env)
        assert r.returncode == 0, r.stderr[-3000:]
        return json.loads(r.stdout.strip().splitlines()[-1])
    first, later = run(), run()
    assert first["key"] == later["key"]
    assert first["calibration_s"] > 0 and later["calibration_s"] == 0
    assert all(r.startswith("kept from an earlier run") or "below" in r or "rays: sorting" in r
               for r in later["reasons"]), later["reasons"]
    assert later["loop"] == ("megakernel" if first["loop"] == "megakernel" else later["loop"])
    assert any("timed" in r for r in later["reasons"])


def test_key_follows_content_not_load_order():
    """The same content in another shape order gives the same key; a moved vertex another, and so
    does another step cap (auto's timings are of the design they ran)."""
    from layerbvh_mitsuba.runtime.adapter import SceneTracer
    a = testing.load(STAIRCASE, RES)
    b = testing.load(STAIRCASE, RES)
    key_a = SceneTracer(a, count_work=False).device_key()
    assert SceneTracer(b, count_work=False).device_key() == key_a
    assert SceneTracer(b, count_work=False, tail_steps=4).device_key() != key_a
    params = mi.traverse(b)
    name = next(k for k in params.keys() if k.endswith("vertex_positions"))
    v = np.array(params[name])
    v[0] += 1e-3
    params[name] = type(params[name])(v)
    params.update()
    assert SceneTracer(b, count_work=False).device_key() != key_a
