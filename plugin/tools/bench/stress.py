"""Deterministic Mitsuba 3 stress scenes (spheres, terrain, soup) at a requested triangle count."""
from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from layerbvh.meshes import uv_sphere

KINDS = ("spheres", "terrain", "soup")
PROG = "gen_stress"
TOLERANCE = 0.05  # the produced triangle count may differ from the request by at most 5%

# -- memory estimate --------------------------------------------------------------------------------

# Per-item sizes of what a scene costs once loaded. These are estimates, not measurements of a
# given run: the layerbvh numbers follow layerbvh/layout.py (64 B triangle records, 64 B inner
# nodes, 8 B leaf ranges, plus a 4 B treelet id per node and per leaf); a binned-SAH tree with
# leaf_size 4 has leaves of 1-4 triangles, so about F / leaf_size * 2 inner nodes is a safe bound.
# Mitsuba keeps its own copy of the mesh (12 B of faces per triangle, 12 B positions and 12 B
# computed normals per vertex: 36 B/tri when V ~ F), and Embree's BVH over it is roughly 100 B
# per triangle (nodes plus its triangle blocks, build scratch excluded). Building the layerbvh
# tree needs far more than the tree itself: its numpy binned-SAH build peaked at ~485 B/tri over
# the loaded mesh (200k and 1M triangles, leaf_size 4), i.e. ~420 B/tri of scratch beyond the BVH.
BVH_TRI_B, BVH_NODE_B, BVH_LEAF_B, BVH_BUILD_B = 64, 64 + 4, 8 + 4, 420
MI_FACE_B, MI_VERTEX_B, EMBREE_TRI_B = 12, 24, 100
PLY_VERTEX_B, PLY_FACE_B, PLY_HEADER_B = 12, 13, 256


def estimate_bytes(triangles: int, leaf_size: int = 4, vertices: int | None = None) -> dict:
    """Estimated bytes of a scene of `triangles` triangles (and `vertices` vertices, default the
    triangle count): `mesh` (binary PLY on disk, also its size as float32/int32 arrays in memory),
    `bvh` (layerbvh Layer BVH), `bvh_build` (scratch while building it), `mitsuba` (Mitsuba's
    mesh copy), `embree` (Embree's BVH) and `total` (all of them together: the layerbvh integrator
    builds its BVH while Mitsuba holds the scene and Embree's BVH).

    An estimate, not a measurement: real use varies with the tree shape and the Mitsuba variant."""
    f = int(triangles)
    v = f if vertices is None else int(vertices)
    leaves = math.ceil(f / leaf_size) * 2  # leaves average ~leaf_size/2 triangles
    nodes = leaves  # a binary tree has one inner node fewer than leaves
    est = {
        "mesh": PLY_HEADER_B + PLY_VERTEX_B * v + PLY_FACE_B * f,
        "bvh": BVH_TRI_B * f + BVH_NODE_B * nodes + BVH_LEAF_B * leaves,
        "bvh_build": BVH_BUILD_B * f,
        "mitsuba": MI_FACE_B * f + MI_VERTEX_B * v,
        "embree": EMBREE_TRI_B * f,
    }
    est["total"] = sum(est.values())
    return est


def available_bytes(meminfo: str = "/proc/meminfo") -> int | None:
    """MemAvailable from /proc/meminfo in bytes, or None where it cannot be read."""
    try:
        for line in Path(meminfo).read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def human(n: float) -> str:
    """Bytes in binary units, e.g. 1.5 GiB."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


# -- plans: counts first, so the memory check needs no mesh --------------------------------------


@dataclass(frozen=True)
class Plan:
    kind: str
    triangles: int  # exactly what will be written
    vertices: int
    params: tuple  # kind-specific sizes (see the plan_* functions)


def plan_spheres(n: int) -> Plan:
    # ~sqrt(N)/2 spheres: enough objects for incoherent bounces, enough triangles per sphere for
    # a deep per-object subtree. At least 10 spheres keeps rounding below 1/(2*10) = 5%.
    count = min(max(round(math.sqrt(n) / 2), 10), 4000)
    k = max(2, round(math.sqrt(n / count / 4)))  # uv_sphere(2k, k+1) has 4 k^2 triangles
    per = 4 * k * k
    count = max(1, round(n / per))
    verts_per = 2 * k * k + 2  # k rings of 2k, plus the poles
    return Plan("spheres", count * per, count * verts_per, (count, k))


def plan_terrain(n: int) -> Plan:
    nx = max(1, round(math.sqrt(n / 2)))  # 2 triangles per grid cell, nx by nz cells
    nz = max(1, round(n / 2 / nx))
    return Plan("terrain", 2 * nx * nz, (nx + 1) * (nz + 1), (nx, nz))


def plan_soup(n: int) -> Plan:
    return Plan("soup", n, 3 * n, (n,))  # unshared vertices: a soup has no connectivity


PLANS = {"spheres": plan_spheres, "terrain": plan_terrain, "soup": plan_soup}

# -- meshes -----------------------------------------------------------------------------------------

# The inside of empty_box.xml's box, kept clear of the walls, the ceiling light and the camera
# (at the origin): x, y in [-1, 1], z in [-3.5, 0.5].
FILL_LO = np.array([-0.95, -0.95, -3.4])
FILL_HI = np.array([0.95, 0.93, -1.0])

# name -> XML of the bsdf; every sphere gets one of these at random.
SPHERE_MATERIALS = {
    "glass": '<bsdf type="dielectric" id="glass">\n'
             '        <float name="int_ior" value="1.5"/>\n        <float name="ext_ior" value="1.0"/>\n    </bsdf>',
    "mirror": '<bsdf type="conductor" id="mirror">\n'
              '        <string name="material" value="Ag"/>\n    </bsdf>',
    "rough_metal": '<bsdf type="roughconductor" id="rough_metal">\n'
                   '        <string name="material" value="Au"/>\n'
                   '        <float name="alpha" value="0.15"/>\n    </bsdf>',
    "diffuse": '<bsdf type="diffuse" id="diffuse">\n'
               '        <rgb name="reflectance" value="0.2, 0.4, 0.8"/>\n    </bsdf>',
}


def grid_cells(count: int, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Centres of a cubic grid over [lo, hi] with at least `count` cells, and the cell size."""
    ext = hi - lo
    cell = float(np.prod(ext) / count) ** (1 / 3)
    while True:
        dims = np.floor(ext / cell).astype(int)
        if dims.min() >= 1 and dims.prod() >= count:
            break
        cell *= 0.97  # shrink until enough cells fit
    idx = np.stack(np.meshgrid(*(np.arange(d) for d in dims), indexing="ij"), -1).reshape(-1, 3)
    # Centre the grid in the region so spare space is split evenly on both sides.
    offset = lo + (ext - dims * cell) / 2
    return offset + (idx + 0.5) * cell, cell


def sphere_meshes(plan: Plan, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Non-overlapping spheres (one per grid cell, jittered), grouped into one mesh per material."""
    count, k = plan.params
    tv, tf = uv_sphere(2 * k, k + 1)
    cells, size = grid_cells(count, FILL_LO, FILL_HI)
    centres = cells[rng.choice(len(cells), count, replace=False)]
    # A radius below half a cell and a jitter of the slack keep every sphere in its own cell:
    # overlapping dielectrics would be physically meaningless nested interfaces.
    radii = size / 2 * rng.uniform(0.35, 0.95, count)
    centres = centres + rng.uniform(-1, 1, (count, 3)) * (size / 2 - radii)[:, None]
    names = list(SPHERE_MATERIALS)
    # A balanced, shuffled assignment: every material appears even for few spheres.
    material = rng.permutation(np.arange(count) % len(names))
    out = {}
    for m, name in enumerate(names):
        sel = np.nonzero(material == m)[0]
        if len(sel):
            v = tv[None] * radii[sel, None, None] + centres[sel, None, :]
            f = tf[None] + (np.arange(len(sel)) * len(tv))[:, None, None]
            out[name] = (v.reshape(-1, 3), f.reshape(-1, 3))
    return out


TERRAIN_SIZE = 30.0  # the terrain covers x, z in [-15, 15]


def terrain_mesh(plan: Plan, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A heightfield y = sum of seeded sines (octaves of random directions and phases)."""
    nx, nz = plan.params
    x = np.linspace(-TERRAIN_SIZE / 2, TERRAIN_SIZE / 2, nx + 1)
    z = np.linspace(-TERRAIN_SIZE / 2, TERRAIN_SIZE / 2, nz + 1)
    gx, gz = np.meshgrid(x, z)  # row i is z[i], column j is x[j]
    y = np.zeros_like(gx)
    for octave in range(8):
        # Frequencies double and amplitudes halve per octave: hills with finer bumps on them.
        freq, amp = 0.25 * 2 ** octave, 1.2 / 2 ** octave
        theta, phase = rng.uniform(0, 2 * np.pi, 2)
        y += amp * np.sin(freq * (np.cos(theta) * gx + np.sin(theta) * gz) + phase)
    verts = np.stack([gx, y, gz], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nz), np.arange(nx), indexing="ij")
    a = (i * (nx + 1) + j).ravel()
    b, c, d = a + 1, a + nx + 1, a + nx + 2
    # (a, c, b) winds counter-clockwise seen from +y, so the normals face up toward the sun.
    faces = np.concatenate([np.stack([a, c, b], -1), np.stack([b, c, d], -1)])
    return {"terrain": (verts, faces)}


def soup_mesh(plan: Plan, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Small triangles of random centres and orientations filling the inside of the box."""
    (n,) = plan.params
    # Edge length ~ 1.5x the mean spacing: the soup is dense enough to occlude, sparse enough
    # that rays reach deep into it, at any N.
    edge = 1.5 * float(np.prod(FILL_HI - FILL_LO) / n) ** (1 / 3)
    centres = rng.uniform(FILL_LO, FILL_HI, (n, 1, 3))
    verts = (centres + rng.uniform(-edge / 2, edge / 2, (n, 3, 3))).reshape(-1, 3)
    faces = np.arange(3 * n).reshape(-1, 3)
    return {"soup": (verts, faces)}


GENERATORS = {"spheres": sphere_meshes, "terrain": terrain_mesh, "soup": soup_mesh}

# -- PLY --------------------------------------------------------------------------------------------

FACE_DTYPE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])  # packed: 13 bytes per face


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> int:
    """Binary little-endian PLY of float32 positions and int32 triangles; returns its size."""
    header = (f"ply\nformat binary_little_endian 1.0\ncomment gen_stress\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rec = np.empty(len(faces), FACE_DTYPE)
    rec["n"] = 3
    rec["i"] = faces
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(np.ascontiguousarray(vertices, "<f4").tobytes())
        fh.write(rec.tobytes())
    return path.stat().st_size


# -- XML --------------------------------------------------------------------------------------------

HEADER = """<?xml version="1.0" encoding="utf-8"?>
<!-- {comment} -->
<scene version="3.0.0">
    <default name="resx" value="{resx}"/>
    <default name="resy" value="{resy}"/>
    <default name="spp" value="{spp}"/>
    <default name="max_depth" value="{max_depth}"/>

    <integrator type="path">
        <integer name="max_depth" value="$max_depth"/>
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="60"/>
        <string name="fov_axis" value="x"/>
        <transform name="to_world">
            <lookat origin="{origin}" target="{target}" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resx"/>
            <integer name="height" value="$resy"/>
            <string name="pixel_format" value="rgb"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""

# empty_box.xml's closed box and ceiling light, verbatim in geometry and materials.
BOX = """
    <bsdf type="diffuse" id="grey">
        <rgb name="reflectance" value="0.7, 0.7, 0.7"/>
    </bsdf>
    <bsdf type="diffuse" id="red">
        <rgb name="reflectance" value="1.0, 0.3, 0.4"/>
    </bsdf>
    <bsdf type="diffuse" id="green">
        <rgb name="reflectance" value="0.3, 1.0, 0.4"/>
    </bsdf>
    <bsdf type="diffuse" id="light_black">
        <rgb name="reflectance" value="0, 0, 0"/>
    </bsdf>
""" + "".join(
    f"""    <shape type="rectangle" id="{sid}">
        <transform name="to_world">
            <matrix value="{m}"/>
        </transform>
        <ref id="{bsdf}"/>
    </shape>
""" for sid, m, bsdf in [
        ("floor", "1 0 0 0 0 0 1 -1 0 -2 0 -1.5 0 0 0 1", "grey"),
        ("ceiling", "1 0 0 0 0 0 -1 1 0 2 0 -1.5 0 0 0 1", "grey"),
        ("back_wall", "1 0 0 0 0 1 0 0 0 0 1 -3.5 0 0 0 1", "grey"),
        ("front_wall", "-1 0 0 0 0 1 0 0 0 0 -1 0.5 0 0 0 1", "grey"),
        ("left_wall", "0 0 1 -1 1 0 0 0 0 2 0 -1.5 0 0 0 1", "red"),
        ("right_wall", "0 0 -1 1 0 1 0 0 2 0 0 -1.5 0 0 0 1", "green"),
    ]) + """    <shape type="rectangle" id="ceiling_light">
        <transform name="to_world">
            <matrix value="0.25 0 0 0 0 0 -1 0.995 0 0.25 0 -2 0 0 0 1"/>
        </transform>
        <ref id="light_black"/>
        <emitter type="area">
            <rgb name="radiance" value="15, 15, 15"/>
        </emitter>
    </shape>
"""

SKY = """
    <emitter type="directional" id="sun">
        <vector name="direction" value="-0.5, -0.8, -0.35"/>
        <rgb name="irradiance" value="3.0, 2.8, 2.4"/>
    </emitter>
    <emitter type="constant" id="sky">
        <rgb name="radiance" value="0.25, 0.35, 0.5"/>
    </emitter>
    <bsdf type="diffuse" id="terrain_bsdf">
        <rgb name="reflectance" value="0.45, 0.4, 0.3"/>
    </bsdf>
"""

SOUP_BSDF = """
    <!-- two-sided: soup triangles face every way, and a one-sided diffuse back face is black -->
    <bsdf type="twosided" id="soup_bsdf">
        <bsdf type="diffuse">
            <rgb name="reflectance" value="0.75, 0.7, 0.6"/>
        </bsdf>
    </bsdf>
"""


def ply_shape(name: str, bsdf: str) -> str:
    # Shape ids get a suffix: Mitsuba ids share one namespace, and the bsdf may have the same name.
    return f"""    <shape type="ply" id="{name}_mesh">
        <string name="filename" value="meshes/{name}.ply"/>
        <ref id="{bsdf}"/>
    </shape>
"""


def scene_xml(plan: Plan, names: list[str], seed: int, res: tuple[int, int], spp: int, max_depth: int) -> str:
    # No "--" here: XML comments may not contain it (pugixml accepts it, other parsers do not).
    comment = (f"generated by scripts/gen_stress.py: {plan.kind}, seed {seed}, "
               f"{plan.triangles} triangles, {plan.vertices} vertices")
    if plan.kind == "terrain":
        view = {"origin": "0, 14, 10", "target": "0, 0, -4"}  # above the terrain, 45 degrees down
    else:
        view = {"origin": "0, 0, 0", "target": "0, 0, -1"}  # empty_box.xml's camera
    xml = HEADER.format(comment=comment, resx=res[0], resy=res[1], spp=spp, max_depth=max_depth, **view)
    if plan.kind == "spheres":
        xml += BOX + "\n    " + "\n    ".join(SPHERE_MATERIALS[n] for n in names) + "\n"
        xml += "".join(ply_shape(n, n) for n in names)
    elif plan.kind == "terrain":
        xml += SKY + ply_shape("terrain", "terrain_bsdf")
    else:
        xml += BOX + SOUP_BSDF + ply_shape("soup", "soup_bsdf")
    return xml + "</scene>\n"


# -- output folder ----------------------------------------------------------------------------------


def write_scene(out: Path, plan: Plan, seed: int, res, spp: int, max_depth: int, force: bool) -> int:
    """Generate into a hidden sibling folder and rename it to `out`, so `out` is never half-written.
    Returns the number of triangles written."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        (tmp / "meshes").mkdir()
        meshes = GENERATORS[plan.kind](plan, np.random.default_rng(seed))
        written = 0
        for name, (v, f) in meshes.items():
            write_ply(tmp / "meshes" / f"{name}.ply", v, f)
            written += len(f)
        (tmp / "scene.xml").write_text(scene_xml(plan, list(meshes), seed, res, spp, max_depth))
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700; the result should look like any folder
        replace_dir(tmp, out, force)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return written


def replace_dir(src: Path, dst: Path, force: bool) -> None:
    """Rename `src` to `dst`; with `force`, a non-empty `dst` is moved aside first, then deleted."""
    if dst.exists() and force and any(dst.iterdir()):
        old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old-", dir=dst.parent))
        os.replace(dst, old / "d")  # move aside first: dst is swapped, never deleted half-way
        os.replace(src, dst)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(src, dst)  # rename(2) replaces an empty folder, refuses a non-empty one


# -- command line -----------------------------------------------------------------------------------


class Refused(Exception):
    """A request this tool will not carry out; the message is the one line printed."""


def parse_args(argv):
    p = argparse.ArgumentParser(prog=PROG, description=__doc__)
    p.add_argument("kind", choices=KINDS)
    p.add_argument("--triangles", type=int, required=True, metavar="N", help="requested triangle count")
    p.add_argument("--out", type=Path, help="output folder (scene.xml, meshes/*.ply)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--res", type=int, nargs=2, default=(128, 128), metavar=("W", "H"))
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--max-depth", type=int, default=8)
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--check-only", action="store_true", help="print the memory estimate and exit")
    a = p.parse_args(argv)
    if not a.check_only and a.out is None:
        p.error("--out is required unless --check-only")
    for name, value, low in [("--triangles", a.triangles, 1000), ("--seed", a.seed, 0), ("--spp", a.spp, 1),
                             ("--max-depth", a.max_depth, -1), ("--res", min(a.res), 1)]:
        if value < low:
            p.error(f"{name} must be >= {low}, got {value}")
    return a


def check_memory(plan: Plan, requested: int) -> dict:
    """Print the counts and the memory estimate; refuse if the estimate exceeds MemAvailable."""
    est = estimate_bytes(plan.triangles, vertices=plan.vertices)
    avail = available_bytes()
    print(f"{PROG}: {plan.kind}: requested {requested} triangles, will write {plan.triangles} "
          f"({plan.vertices} vertices)")
    print(f"{PROG}: memory estimate: mesh on disk {human(est['mesh'])}, layerbvh BVH {human(est['bvh'])} "
          f"(+{human(est['bvh_build'])} while building), "
          f"Mitsuba mesh {human(est['mitsuba'])}, Embree {human(est['embree'])}, total {human(est['total'])}; "
          f"available {human(avail) if avail is not None else 'unknown'}")
    if avail is not None and est["total"] > avail:
        raise Refused(f"{requested} triangles ({plan.kind}: {plan.triangles}) need an estimated {human(est['total'])} "
                      f"({est['total']} B) but only {human(avail)} ({avail} B) is available")
    return est


def run(a) -> None:
    plan = PLANS[a.kind](a.triangles)
    # Any plan is within 5% by construction; this guards the arithmetic of the plan_* functions.
    if abs(plan.triangles - a.triangles) > TOLERANCE * a.triangles:
        raise Refused(f"cannot make {a.triangles} triangles of {a.kind} within 5% (got {plan.triangles})")
    check_memory(plan, a.triangles)
    if plan.vertices >= 2 ** 31:  # the PLY faces store int32 vertex indices
        raise Refused(f"{a.triangles} triangles of {a.kind} need {plan.vertices} vertices, "
                      "more than int32 indices hold")
    if a.check_only:
        return
    out = a.out
    # Checked before generating, so a refusal costs nothing; --force never replaces a plain file.
    if out.exists() and not out.is_dir():
        raise Refused(f"{out} exists and is not a folder")
    if out.exists() and not a.force and any(out.iterdir()):
        raise Refused(f"{out} exists and is not an empty folder (use --force to replace it)")
    t0 = time.perf_counter()
    written = write_scene(out, plan, a.seed, tuple(a.res), a.spp, a.max_depth, a.force)
    size = sum(p.stat().st_size for p in (out / "meshes").iterdir())
    print(f"{PROG}: wrote {out / 'scene.xml'}: {written} triangles ({written / a.triangles - 1:+.2%} of the "
          f"request), meshes {human(size)}, in {time.perf_counter() - t0:.2f} s")


def main(argv=None) -> int:
    a = parse_args(argv)
    try:
        run(a)
    except Refused as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
