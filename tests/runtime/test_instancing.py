"""Mitsuba instances through our traversal: same-seed images in every mode, hit records filled as Embree fills them,
memory, per-shape tests and refusals."""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import layerbvh_mitsuba  # noqa: F401  (registers the integrator)
from layerbvh.backend import from_numpy
from layerbvh_mitsuba.runtime import scene_geometry
from layerbvh_mitsuba import testing
from layerbvh_mitsuba.runtime.adapter import SceneTracer
from layerbvh_mitsuba.runtime.scene_geometry import MAX_PER_SHAPE_TESTS, UnsupportedShapeError

SCENES = Path(__file__).resolve().parents[2] / "scenes"
BUNNY_TRIANGLES = 69_451


# Every mode on Mitsuba's own instancing scene; the 24-bunny scene with the default traversal
# (its layer modes compile ~25 wavefront kernels of 1-2 s each for its many materials: the modes'
# hits are checked bit for bit against per_ray on 24 instances in tests/engine/test_engine_instances.py).
@pytest.mark.parametrize("name,traversal", [("instancing", "per_ray"), ("instancing", "layer_sorted"),
                                            ("instancing", "layer_unsorted"), ("instanced_bunnies", "auto")])
def test_instanced_scene_matches_stock(name, traversal, tmp_path):
    # instanced_bunnies at max_depth 3: its 24 small bunnies sit far (relative to their
    # triangles' size) from the rays' origins, where the float32 barycentrics of any triangle
    # test (Embree's and ours) are noisy to ~1e-3; same-seed paths then drift apart after a few
    # bounces. A flattened copy (no instances) drifts alike: 96.5% of pixels within 1e-3 at
    # max_depth 10, 95.8% instanced (docs/guide.md, "Instances"); the Z-test below covers full depth.
    #
    # Even at max_depth 3 one pixel of 1024 falls outside the same-seed tolerance, on AVX-512 and
    # with LAYERBVH_LLVM_ISA=avx2 alike (docs/cpu_margins/table.json): the default criterion
    # (99.9%) has room for exactly that one, and another CPU's rounding may move a second (issue
    # 64). 1% of pixels leaves room for ten; the mean criterion (1e-4 of the mean pixel, measured
    # 0.23 of it) is what a real error (a 2% albedo: every pixel) fails by far.
    params = {"max_depth": 3} if name == "instanced_bunnies" else {}
    room = {"min_frac": 0.99} if name == "instanced_bunnies" else {}
    r = testing.assert_matches_stock(SCENES / f"{name}.xml", spp=8, res=(32, 32), traversal=traversal,
                                     diff_dir=tmp_path, **room, **params)
    assert r.mean_ref > 0.01, "the scene should not render black"


def test_an_instance_scaled_to_zero_renders_as_stock_renders_it(tmp_path):
    """Issue 56: an instance whose to_world scales by 0 (a hidden copy) or along one axis
    (flattened onto a plane) was refused as singular. Stock renders both as absent (measured: the
    image equals the scene without them, bit for bit); ours leaves them out and matches stock, with
    a normal instance of the same group beside them."""
    inst = ('<shape type="instance"><ref id="g"/>'
            '<transform name="to_world"><scale value="{}"/><translate y="{}"/></transform></shape>')
    path = tmp_path / "hidden.xml"
    path.write_text(f"""<scene version="3.0.0"><sensor type="perspective">
        <transform name="to_world"><lookat origin="0,3,4" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film></sensor>
        <shape type="shapegroup" id="g"><shape type="cube"/></shape>
        {inst.format("0", 0.5)} {inst.format("1, 0, 1", 0.5)} {inst.format("0.5", -0.5)}
        <shape type="rectangle">
          <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/></transform></shape>
        <emitter type="directional"><vector name="direction" value="0.3,-1,0.2"/></emitter>
        <emitter type="constant"><rgb name="radiance" value="0.3"/></emitter></scene>""")
    geo = scene_geometry.collect_geometry(mi.load_file(str(path)))
    # the floor, the visible cube (the third instance)
    assert [p.instance for p in geo.placements] == [None, 2], geo.placements
    r = testing.assert_matches_stock(path, spp=4, res=(16, 16), traversal="per_ray")
    assert r.mean_ref > 0.01


# The independent-seed test's configuration (verdict.independent_seed_test), shared with its
# negative control below: 36 pixels (one failing fails the rule of at most 1% failing), 4096
# samples per pixel a side.
Z_TEST = {"spp": 4096, "res": (6, 6)}


def test_instanced_bunnies_pass_the_z_test_at_full_depth():
    r = testing.assert_statistically_matches_stock(SCENES / "instanced_bunnies.xml", traversal="per_ray", **Z_TEST)
    assert r.pixels == 36


def test_instanced_bunnies_z_test_catches_a_2_percent_albedo_change():
    """Negative control of the Z-test above: it must fail when one material's albedo (the grey of
    the floor, ceiling, back and front walls) changes by 2%. Measured: 4 of 36 pixels fail,
    smallest p-value 5.7e-6 against the threshold 2.8e-4; the test above: every pixel passes,
    smallest p-value 9.9e-4."""
    def brighter_grey(params):
        params["grey.reflectance.value"] = params["grey.reflectance.value"] * 1.02
    r = testing.independent_seeds_vs_stock(SCENES / "instanced_bunnies.xml", traversal="per_ray", modify=brighter_grey,
                                          **Z_TEST)
    assert not r.passed, r.family.summary()


def _camera_rays(origin, lo, hi, n, seed):
    rng = np.random.default_rng(seed)
    d = rng.uniform(lo, hi, (n, 3)) - np.asarray(origin, np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(np.asarray(origin, np.float32), (n, 3))
    # (through from_numpy: memory Dr.Jit maps at numpy's chance alignment makes the kernels that
    # read it hash differently from run to run, so the kernel cache never finds them)
    return mi.Ray3f(mi.Point3f(*(from_numpy(mi.Float, o[:, c]) for c in range(3))),
                    mi.Vector3f(*(from_numpy(mi.Float, d[:, c].astype(np.float32)) for c in range(3))))


@pytest.mark.parametrize("traversal", ["per_ray", "layer_sorted", "inline"])
def test_hit_records_are_filled_as_embree_fills_them(traversal):
    """instanced_bunnies has hits on the scene's own meshes (walls), on instanced meshes and on
    an instanced analytic sphere: `shape`, `instance`, shape_index, prim_index, t and the
    surface interaction Mitsuba computes from them must be stock's."""
    scene = testing.load(SCENES / "instanced_bunnies.xml", (32, 32))
    tracer = SceneTracer(scene, "per_ray" if traversal == "inline" else traversal)
    ray = _camera_rays([0, 0, 0], [-1, -1.05, -3.5], [1, -0.3, -1.5], 40_000, seed=1)
    active = dr.full(mi.Bool, True, dr.width(ray.o))
    ours = tracer.intersect_inline(ray, active) if traversal == "inline" else tracer.intersect(ray, active)
    stock = scene.ray_intersect_preliminary(ray)
    valid_o, valid_s = ours.is_valid().numpy(), stock.is_valid().numpy()
    n = len(valid_s)
    assert (valid_o != valid_s).sum() <= 1e-3 * n
    both = valid_o & valid_s
    same_inst = (ours.instance == stock.instance).numpy()
    same_shape = (ours.shape == stock.shape).numpy()
    same_index = (ours.shape_index.numpy() == stock.shape_index.numpy()) & \
        (ours.prim_index.numpy() == stock.prim_index.numpy())
    agree = both & same_inst & same_shape & same_index
    # Ties and edges decided otherwise by Embree: a handful of rays at most.
    assert agree.sum() >= both.sum() - 1e-3 * n, f"{both.sum() - agree.sum()} of {both.sum()} hits disagree"
    in_instance = both & (stock.instance != None).numpy()  # noqa: E711
    sphere = in_instance & (stock.shape_index.numpy() == 1)  # the shapegroup's second shape: the ball
    assert in_instance.sum() > 0.2 * n and (both & ~in_instance).sum() > 0.05 * n and sphere.sum() > 20, \
        "rays should hit instanced meshes, the scene's own meshes and instanced spheres"
    assert (ours.shape == None).numpy()[in_instance & agree].all(), \
        "an instance hit leaves `shape` null, as Embree does"  # noqa: E711
    t_o, t_s = ours.t.numpy(), stock.t.numpy()
    assert np.quantile(np.abs(t_o[agree] - t_s[agree]) / t_s[agree], 0.999) < 1e-4
    si_o = ours.compute_surface_interaction(ray, mi.RayFlags.All, active)
    si_s = stock.compute_surface_interaction(ray, mi.RayFlags.All, active)
    dr.eval(si_o.p, si_o.n, si_o.uv, si_s.p, si_s.n, si_s.uv)  # (one kernel per side, not one per field read)
    # Same triangle, t within float rounding: hit points agree to ~1e-5; the normals of small
    # instanced spheres (radius ~0.04) and texture uv (the bunny's tiny triangles: barycentrics
    # noisy to ~1e-3 in Embree's float32 test and ours alike) to ~1e-4.
    for field, tol in (("p", 1e-4), ("n", 1e-3), ("uv", 1e-3)):
        a, b = (np.array(getattr(si, field)).T[agree] for si in (si_o, si_s))
        assert np.quantile(np.abs(a - b).max(1), 0.999) < tol, field
    assert (si_o.shape == si_s.shape).numpy()[agree].all() and (si_o.instance == si_s.instance).numpy()[agree].all()


def test_memory_grows_with_unique_geometry():
    """24 bunnies are stored as one: triangle records for the unique triangles only, and a few
    hundred bytes per instance."""
    scene = testing.load(SCENES / "instanced_bunnies.xml", (8, 8))
    tracer = SceneTracer(scene, "layer_sorted")
    st = tracer.bvh.stats
    own = len(tracer.geometry.groups[0].faces)  # walls and light
    assert st.triangles == BUNNY_TRIANGLES + own and st.instances == 25 and st.groups == 2
    assert st.placed_triangles == 24 * BUNNY_TRIANGLES + own
    assert st.bytes["tris"] == 64 * st.triangles
    assert st.total_bytes < 1.2 * 64 * 2 * st.triangles, "nodes + triangles: about those of the unique geometry"


def test_nested_instancing_is_refused_by_name(monkeypatch):
    """Mitsuba 3.9 refuses a shapegroup holding an instance at load time, so no scene we are
    given can hold one; our own refusal (scene_geometry.collect_geometry), there should a later Mitsuba
    allow it, is exercised by showing the adapter a shapegroup whose children include an
    instance (and one that includes a shapegroup)."""
    with pytest.raises(RuntimeError, match="Nested instancing is not permitted"):
        mi.load_string("""<scene version="3.0.0"><shape type="shapegroup" id="a"><shape type="sphere"/></shape>
            <shape type="shapegroup" id="b"><shape type="instance"><ref id="a"/></shape></shape></scene>""")
    scene = mi.load_dict(_box_with({"grp": {"type": "shapegroup", "ball": {"type": "sphere", "radius": 0.1}},
                                    "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"}}}))
    SceneTracer(scene, "per_ray")  # as loaded: one level of instancing, traced
    inst = next(sh for sh in scene.shapes() if sh.class_name() == "Instance")
    group = next(obj for _, obj in scene_geometry._children(scene) if scene_geometry._is_shapegroup(obj))
    real = scene_geometry._children
    for nested, what in ((inst, r"Instance 'inst'"), (group, r"ShapeGroup\w* 'grp'")):
        monkeypatch.setattr(scene_geometry, "_children", lambda obj, nested=nested: real(obj) + [("nested", nested)]
                            if scene_geometry._is_shapegroup(obj) else real(obj))
        with pytest.raises(UnsupportedShapeError,
                           match=rf"{what} in shapegroup 'grp': nested instancing is not supported"):
            SceneTracer(scene, "per_ray")


def _ellipsoids(n: int) -> mi.TensorXf:
    rng = np.random.default_rng(n)
    data = np.zeros((n, 10), np.float32)
    data[:, 0:3] = rng.uniform([-0.6, -0.8, -2.9], [0.6, -0.2, -2.0], (n, 3))
    data[:, 3:6] = rng.uniform(0.08, 0.25, (n, 3))
    q = rng.normal(size=(n, 4))
    data[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return mi.TensorXf(data)


def _box_with(shapes: dict) -> dict:
    return {"type": "scene",
            "sensor": {"type": "perspective", "fov": 60,
                       "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, -1], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 8}},
            "floor": {"type": "rectangle",
                      "to_world": mi.ScalarTransform4f().translate([0, -1, -1.5]).rotate([1, 0, 0], -90)
                                                        .scale([1, 2, 1])},
            "back": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -3.5])},
            "light": {"type": "constant"}, **shapes}


@pytest.mark.parametrize("where", ["scene", "instance"])
def test_ellipsoids_match_stock(where):
    ell = {"type": "ellipsoids", "data": _ellipsoids(5),
           "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.3, 0.2]}}}
    if where == "scene":
        shapes = {"ell": ell}
    else:
        shapes = {"grp": {"type": "shapegroup", "ell": ell},
                  "i0": {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"}},
                  "i1": {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"},
                         "to_world": mi.ScalarTransform4f().translate([0.3, 0.35, -0.2]).rotate([0, 1, 0], 40)}}
    scene = mi.load_dict(_box_with(shapes))
    plain = mi.load_dict(_box_with({}))
    ref = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 6}), spp=8, seed=0))
    without = np.array(mi.render(plain, integrator=mi.load_dict({"type": "path", "max_depth": 6}), spp=8, seed=0))
    assert np.mean(np.abs(ref - without).max(-1) > 1e-2) > 0.05, "the ellipsoids should be visible"
    for traversal in ("per_ray", "layer_sorted"):
        ours = np.array(mi.render(scene, integrator=mi.load_dict({"type": "layerbvh", "traversal": traversal,
                                                                   "max_depth": 6}), spp=8, seed=0))
        d = np.abs(ref - ours).max(-1)
        assert np.mean(d <= 1e-3) >= 0.999, f"{traversal}: max |diff| {d.max()}"


def test_large_ellipsoid_clouds_and_many_instanced_spheres_are_refused_by_name():
    scene = mi.load_dict(_box_with({"cloud": {"type": "ellipsoids", "data": _ellipsoids(MAX_PER_SHAPE_TESTS + 1)}}))
    with pytest.raises(UnsupportedShapeError, match=rf"Ellipsoids 'cloud'.*holds {MAX_PER_SHAPE_TESTS + 1} ellipsoids"):
        SceneTracer(scene, "per_ray")
    many = {"grp": {"type": "shapegroup", "ball": {"type": "sphere", "radius": 0.05}}}
    for k in range(MAX_PER_SHAPE_TESTS + 1):
        many[f"i{k}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"},
                         "to_world": mi.ScalarTransform4f().translate([0.01 * k, -0.5, -2.5])}
    with pytest.raises(UnsupportedShapeError, match=rf"place {MAX_PER_SHAPE_TESTS + 1} analytic shapes"):
        SceneTracer(mi.load_dict(_box_with(many)), "per_ray")


def _curve_file(tmp_path) -> str:
    path = tmp_path / "curve.txt"
    path.write_text("-0.5 -0.5 -2 0.05\n-0.2 -0.2 -2 0.05\n0.2 -0.4 -2 0.05\n0.5 -0.3 -2 0.05\n")
    return str(path)


@pytest.mark.parametrize("kind", ["ellipsoidsmesh", "linearcurve", "bsplinecurve", "sdfgrid", "curve_in_shapegroup"])
def test_other_shapes_are_refused_by_name(kind, tmp_path):
    """Shapes whose per-shape routine Mitsuba does not offer on the LLVM variants (curves, SDF
    grids) or that stock traces otherwise than their triangles (ellipsoidsmesh: back faces
    culled) are refused, naming the shape and its plugin type."""
    grid = np.linspace(0, 1, 8, dtype=np.float32)
    x, y, z = np.meshgrid(grid, grid, grid, indexing="ij")
    sdf = (np.sqrt((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2) - 0.3)[..., None].astype(np.float32)
    shapes = {"ellipsoidsmesh": {"type": "ellipsoidsmesh", "data": _ellipsoids(3)},
              "linearcurve": {"type": "linearcurve", "filename": _curve_file(tmp_path)},
              "bsplinecurve": {"type": "bsplinecurve", "filename": _curve_file(tmp_path)},
              "sdfgrid": {"type": "sdfgrid", "grid": mi.TensorXf(sdf)}}
    if kind == "curve_in_shapegroup":
        scene = mi.load_dict(_box_with({"grp": {"type": "shapegroup", "odd": shapes["linearcurve"]},
                                        "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"}}}))
        message = r"LinearCurve 'odd' in shapegroup 'grp' \(plugin type 'linearcurve'\) is not supported"
    else:
        scene = mi.load_dict(_box_with({"odd": shapes[kind]}))
        message = rf"'odd' \(plugin type '{kind}'\) is not supported"
    with pytest.raises(UnsupportedShapeError, match=message):
        SceneTracer(scene, "per_ray")
