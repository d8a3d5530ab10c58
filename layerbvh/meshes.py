"""The engine's test and benchmark inputs (numpy only): procedural meshes, a PLY/OBJ reader, camera/incoherent rays."""
from __future__ import annotations

import math
from pathlib import Path

import drjit as dr
import numpy as np

from .backend import from_numpy
from .inputs import check_mesh


def device_rays(m, o: np.ndarray, d: np.ndarray):
    """Origins and directions (N, 3) as evaluated Array3f of Dr.Jit module `m` (the ray batch a
    benchmark moves to the device once, outside its timing)."""
    o_dev = m.Array3f(*(from_numpy(m.Float, o[:, c]) for c in range(3)))
    d_dev = m.Array3f(*(from_numpy(m.Float, d[:, c]) for c in range(3)))
    dr.eval(o_dev, d_dev)
    return o_dev, d_dev


# -- procedural meshes ------------------------------------------------------------------------------


def uv_sphere(n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed unit UV sphere with 2 * n_lon * (n_lat - 1) triangles and no degenerate ones.

    The poles are single vertices (fans), so no zero-area triangles sit at the poles."""
    if n_lon < 3 or n_lat < 2:
        raise ValueError(f"uv_sphere needs n_lon >= 3 and n_lat >= 2, got {n_lon}, {n_lat}")
    theta = np.pi * np.arange(1, n_lat) / n_lat  # ring latitudes, poles excluded
    phi = 2 * np.pi * np.arange(n_lon) / n_lon
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), ct * np.ones_like(phi), st * np.sin(phi)], -1).reshape(-1, 3)
    top, bottom = 0, 1 + len(ring)
    verts = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]])

    def vid(r, c):  # ring r, column c (wrapping) -> vertex index
        return 1 + r * n_lon + c % n_lon

    c = np.arange(n_lon)
    cap_top = np.stack([np.full(n_lon, top), vid(0, c + 1), vid(0, c)], -1)
    cap_bot = np.stack([np.full(n_lon, bottom), vid(n_lat - 2, c), vid(n_lat - 2, c + 1)], -1)
    r, c = np.meshgrid(np.arange(n_lat - 2), np.arange(n_lon), indexing="ij")
    r, c = r.ravel(), c.ravel()
    a, b, d, e = vid(r, c), vid(r, c + 1), vid(r + 1, c), vid(r + 1, c + 1)
    bands = np.concatenate([np.stack([a, b, e], -1), np.stack([a, e, d], -1)])
    faces = np.concatenate([cap_top, bands, cap_bot]).astype(np.int64)
    return verts.astype(np.float64), faces


def _sphere_resolution(tris_per_sphere: int) -> tuple[int, int]:
    # n_lon = 2 * (n_lat - 1) keeps the quads roughly square: T = 4 * (n_lat - 1)^2.
    k = max(2, round(math.sqrt(max(tris_per_sphere, 16) / 4)))
    return 2 * k, k + 1


def sphere_soup(n_spheres: int, tris_per_sphere: int = 960, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`n_spheres` UV spheres of random radii and orientations, centred in [0, 1]^3 and overlapping.

    Returns (vertices float32 (V, 3), faces int64 (F, 3)); the same seed gives the same mesh."""
    if n_spheres < 1:
        raise ValueError(f"n_spheres must be >= 1, got {n_spheres}")
    tv, tf = uv_sphere(*_sphere_resolution(tris_per_sphere))
    rng = np.random.default_rng(seed)
    # Radii spread ~20x around the mean centre spacing: overlapping boxes and a mix of
    # large and small objects, so the SAH tree is deep and uneven, as in real scenes.
    spacing = n_spheres ** (-1 / 3)
    radii = spacing * np.exp(rng.uniform(np.log(0.08), np.log(1.5), n_spheres))
    centers = rng.uniform(0.0, 1.0, (n_spheres, 3))
    # Random rotations keep the tessellation from lining up with the axes (axis-aligned
    # triangles make unrepresentatively tight boxes).
    q = rng.normal(size=(n_spheres, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rot = _quat_to_matrix(q)
    verts = np.einsum("sij,vj->svi", rot, tv) * radii[:, None, None] + centers[:, None, :]
    faces = tf[None] + (np.arange(n_spheres) * len(tv))[:, None, None]
    return verts.reshape(-1, 3).astype(np.float32), faces.reshape(-1, 3)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def procedural_mesh(target_triangles: int, seed: int = 0, tris_per_sphere: int = 960) -> tuple[np.ndarray, np.ndarray]:
    """A sphere soup with at least `target_triangles` triangles (within one sphere of it)."""
    if target_triangles < 1:
        raise ValueError(f"target_triangles must be >= 1, got {target_triangles}")
    tris_per_sphere = min(tris_per_sphere, max(16, target_triangles))
    n_lon, n_lat = _sphere_resolution(tris_per_sphere)
    per = 2 * n_lon * (n_lat - 1)
    return sphere_soup(math.ceil(target_triangles / per), tris_per_sphere, seed)


def turned_slivers(cols: int = 1000, n: int = 3000, seed: int = 0):
    """A flat strip of 2 x `cols` slivers (1e-3 x 1000, aspect 1e6) turned at random, and `n` rays
    aimed inside it from either side: every box overlaps the others, so each ray walks most of the
    tree (hundreds of wavefront steps). Returns float32 (vertices, faces, origins, directions)."""
    rng = np.random.default_rng(seed)
    bottom = np.stack([np.arange(cols + 1) * 1e-3, np.zeros(cols + 1), np.zeros(cols + 1)], 1)
    v = np.concatenate([bottom, bottom + [0.0, 1000.0, 0.0]])
    i = np.arange(cols)
    f = np.concatenate([np.stack([i, i + 1, cols + 1 + i], 1), np.stack([i + 1, cols + 2 + i, cols + 1 + i], 1)])
    turn, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    v = (v - [cols * 1e-3 / 2, 500.0, 0.0]) @ turn.T
    target = np.stack([rng.uniform(-0.49, 0.49, n) * cols * 1e-3, rng.uniform(-0.49, 0.49, n) * 1e3,
                       np.zeros(n)], 1) @ turn.T
    o = target + turn[:, 2] * rng.uniform(1, 100, (n, 1)) * np.where(rng.random((n, 1)) < 0.5, 1.0, -1.0)
    return v.astype(np.float32), f, o.astype(np.float32), (target - o).astype(np.float32)


# -- rays -------------------------------------------------------------------------------------------


def _bounds(vertices) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be a non-empty (V, 3) array, got shape {v.shape}")
    return v.min(0), v.max(0)


def camera_rays(vertices, n: int, seed: int = 0, fov_deg: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """`n` pinhole-camera rays from one point outside the mesh's bounds, aimed at its centre.

    Pixels are visited in raster order (row by row) over a square image just large enough for
    `n`; the seed picks the viewing direction (y is up). Returns float32 (origins, directions)."""
    lo, hi = _bounds(vertices)
    center, radius = (lo + hi) / 2, max(np.linalg.norm(hi - lo) / 2, 1e-6)
    rng = np.random.default_rng(seed)
    azimuth, elevation = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10, 35))
    back = np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)])
    half = np.tan(np.radians(fov_deg) / 2)
    # Frame the bounding sphere's middle 80%: the corners of a box rarely hold geometry, and this
    # keeps the camera outside the bounding sphere (distance > radius) for fov < ~106 degrees.
    eye = center + back * (0.8 * radius / half)
    forward = -back
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    width = max(1, math.ceil(math.sqrt(n)))
    idx = np.arange(n)
    px = ((idx % width) + 0.5) / width * 2 - 1
    py = 1 - ((idx // width) + 0.5) / width * 2
    d = forward[None] + half * (px[:, None] * right[None] + py[:, None] * up[None])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, (n, 3))
    return np.ascontiguousarray(o, np.float32), d.astype(np.float32)


def incoherent_rays(vertices, n: int, seed: int = 0, enlarge: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """`n` rays with origins uniform in the mesh's bounds (grown on each side by `enlarge` of the
    largest extent) and directions uniform on the sphere. Returns float32 (origins, directions)."""
    lo, hi = _bounds(vertices)
    # Padding by the largest extent keeps a flat mesh's box from having zero thickness, which
    # would start every ray on the mesh's plane.
    pad = max((hi - lo).max(), 1e-6) * enlarge
    rng = np.random.default_rng(seed)
    o = rng.uniform(lo - pad, hi + pad, (n, 3))
    d = rng.normal(size=(n, 3))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where(norm > 1e-12, d / np.maximum(norm, 1e-12), [0.0, 0.0, 1.0])
    return o.astype(np.float32), d.astype(np.float32)


# -- loading ----------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def load_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a PLY (ascii or binary) or OBJ file: (vertices float32 (V, 3), faces int64 (F, 3)).

    Polygons are split into fans. Raises ValueError naming the file and the problem for anything
    unsupported or malformed."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ValueError(f"{path}: cannot read mesh file ({e.strerror or e})") from e
    suffix = path.suffix.lower()
    if suffix == ".ply" or (suffix != ".obj" and data[:4] in (b"ply\n", b"ply\r")):
        v, f = _load_ply(path, data)
    elif suffix == ".obj":
        v, f = _load_obj(path, data)
    else:
        raise ValueError(f"{path}: unsupported mesh format {suffix or '(no extension)'!r}; expected .ply or .obj")
    return _checked(path, v, f)


def _checked(path, v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(f) == 0:
        raise ValueError(f"{path}: mesh has no faces")
    if f.min() < 0 or f.max() >= len(v):
        bad = int(np.nonzero((f < 0).any(1) | (f >= len(v)).any(1))[0][0])
        raise ValueError(f"{path}: face {bad} uses vertex index {f[bad].tolist()} but there are {len(v)} vertices")
    return check_mesh(v, f, name=str(path))


def _fan(polygons: list[np.ndarray], path, what: str) -> np.ndarray:
    """Fan triangles of polygons of any sizes, in file order (so triangle i matches other loaders)."""
    sizes = np.array([len(p) for p in polygons], np.int64)
    if (sizes < 3).any():
        i = int(np.nonzero(sizes < 3)[0][0])
        raise ValueError(f"{path}: {what} {i} has {sizes[i]} vertices; a face needs at least 3")
    flat = np.concatenate(polygons).astype(np.int64)
    starts = np.cumsum(sizes) - sizes
    n_tris = sizes - 2
    first = np.repeat(starts, n_tris)
    # j runs 1 .. k-2 within each polygon: triangle (p0, pj, pj+1).
    j = np.arange(n_tris.sum()) - np.repeat(np.cumsum(n_tris) - n_tris, n_tris) + 1
    return np.stack([flat[first], flat[first + j], flat[first + j + 1]], -1)


def _fan_uniform(polys: np.ndarray) -> np.ndarray:
    """(P, k) polygons -> (P * (k - 2), 3) fan triangles, each polygon's triangles consecutive."""
    p, k = polys.shape
    j = np.arange(1, k - 1)
    tris = np.stack([np.broadcast_to(polys[:, :1], (p, k - 2)), polys[:, j], polys[:, j + 1]], -1)
    return tris.reshape(-1, 3).astype(np.int64)


# PLY


def _ply_header(path, data: bytes):
    """(format, elements, body offset); elements are [name, count, [(prop, type, list count type | None)]]."""
    if not data.startswith(b"ply"):
        raise ValueError(f"{path}: not a PLY file (missing 'ply' magic)")
    end = data.find(b"end_header")
    if end < 0:
        raise ValueError(f"{path}: PLY header has no 'end_header'")
    nl = data.find(b"\n", end)
    body = len(data) if nl < 0 else nl + 1
    fmt, elements = None, []
    for raw in data[:end].decode("ascii", "replace").splitlines()[1:]:
        tok = raw.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in _PLY_FORMATS:
                raise ValueError(f"{path}: unsupported PLY format {' '.join(tok[1:])!r}")
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3 and tok[2].isdigit():
            elements.append([tok[1], int(tok[2]), []])
        elif tok[0] == "property" and elements:
            elements[-1][2].append(_ply_property(path, tok))
        else:
            raise ValueError(f"{path}: bad PLY header line {raw.strip()!r}")
    if fmt is None:
        raise ValueError(f"{path}: PLY header has no 'format' line")
    return fmt, elements, body


def _ply_property(path, tok):
    if tok[1] == "list":
        if len(tok) != 5 or tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
            raise ValueError(f"{path}: unsupported PLY list property {' '.join(tok)!r}")
        if _PLY_TYPES[tok[2]][0] == "f":
            raise ValueError(f"{path}: PLY list count type must be an integer, got {tok[2]!r}")
        return tok[4], _PLY_TYPES[tok[3]], _PLY_TYPES[tok[2]]
    if len(tok) != 3 or tok[1] not in _PLY_TYPES:
        raise ValueError(f"{path}: unsupported PLY property {' '.join(tok)!r}")
    return tok[2], _PLY_TYPES[tok[1]], None


def _load_ply(path, data: bytes):
    fmt, elements, pos = _ply_header(path, data)
    reader = _PlyAscii(path, data[pos:]) if fmt == "ascii" else _PlyBinary(path, data, pos, _PLY_FORMATS[fmt])
    vertices = faces = None
    for name, count, props in elements:
        cols = reader.element(name, count, props)
        if name == "vertex":
            vertices = _ply_vertices(path, cols)
        elif name == "face":
            faces = _ply_faces(path, cols, count)
    if vertices is None:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    if faces is None:
        raise ValueError(f"{path}: PLY file has no 'face' element (point clouds are not supported)")
    return vertices, faces


def _ply_vertices(path, cols: dict) -> np.ndarray:
    missing = [c for c in "xyz" if c not in cols]
    if missing:
        plural = "ies" if len(missing) > 1 else "y"
        raise ValueError(f"{path}: PLY vertex element lacks propert{plural} {', '.join(missing)}")
    return np.stack([np.asarray(cols[c], np.float64) for c in "xyz"], -1)


def _ply_faces(path, cols: dict, count: int) -> np.ndarray:
    key = next((k for k in ("vertex_indices", "vertex_index") if k in cols), None)
    if key is None:
        raise ValueError(f"{path}: PLY face element has no 'vertex_indices' list property")
    lists = cols[key]
    if isinstance(lists, np.ndarray) and lists.ndim == 2:  # every face has the same size
        if lists.shape[1] < 3:
            raise ValueError(f"{path}: PLY faces have {lists.shape[1]} vertices; a face needs at least 3")
        return _fan_uniform(lists.astype(np.int64))
    return _fan([np.asarray(p, np.int64) for p in lists], path, "PLY face")


class _PlyBinary:
    """Reads binary PLY elements; rows are parsed as one structured array when list sizes are uniform."""

    def __init__(self, path, data: bytes, pos: int, order: str):
        self.path, self.data, self.pos, self.order = path, data, pos, order

    def element(self, name: str, count: int, props: list) -> dict:
        counts = self._first_row_counts(name, props) if count else [0] * len(props)
        dtype = np.dtype(self._row_dtype(props, counts))
        rows = None
        if self.pos + count * dtype.itemsize <= len(self.data):
            rows = np.frombuffer(self.data, dtype, count, self.pos)
            if not all((rows[f"n{i}"] == c).all() for i, c in enumerate(counts) if props[i][2]):
                rows = None
        if rows is None:
            return self._element_slow(name, count, props)
        self.pos += count * dtype.itemsize
        return {p[0]: rows[f"p{i}"] for i, p in enumerate(props)}

    def _row_dtype(self, props, counts):
        fields = []
        for i, ((_, t, lt), c) in enumerate(zip(props, counts)):
            if lt:
                fields.append((f"n{i}", self.order + lt))
                fields.append((f"p{i}", self.order + t, (c,)))
            else:
                fields.append((f"p{i}", self.order + t))
        return fields

    def _first_row_counts(self, name, props) -> list[int]:
        pos, counts = self.pos, []
        for _, t, lt in props:
            if lt:
                c = int(self._scalar(name, lt, pos))
                counts.append(c)
                pos += np.dtype(lt).itemsize + c * np.dtype(t).itemsize
            else:
                counts.append(0)
                pos += np.dtype(t).itemsize
        return counts

    def _scalar(self, name, t, pos):
        size = np.dtype(t).itemsize
        if pos + size > len(self.data):
            raise ValueError(f"{self.path}: PLY file ends inside element {name!r}")
        return np.frombuffer(self.data, self.order + t, 1, pos)[0]

    def _element_slow(self, name, count, props) -> dict:
        # Mixed polygon sizes: walk row by row (only faces of mixed sizes, so rare).
        cols = {p[0]: [] for p in props}
        pos = self.pos
        for _ in range(count):
            for pname, t, lt in props:
                if lt:
                    c = int(self._scalar(name, lt, pos))
                    pos += np.dtype(lt).itemsize
                    size = c * np.dtype(t).itemsize
                    if pos + size > len(self.data):
                        raise ValueError(f"{self.path}: PLY file ends inside element {name!r}")
                    cols[pname].append(np.frombuffer(self.data, self.order + t, c, pos))
                    pos += size
                else:
                    cols[pname].append(self._scalar(name, t, pos))
                    pos += np.dtype(t).itemsize
        self.pos = pos
        return {k: (np.array(v) if v and np.ndim(v[0]) == 0 else v) for k, v in cols.items()}


class _PlyAscii:
    """Reads ascii PLY elements from a token stream; uniform rows are parsed with one reshape."""

    def __init__(self, path, body: bytes):
        self.path = path
        self.tokens = body.split()
        self.pos = 0

    def element(self, name: str, count: int, props: list) -> dict:
        if not any(lt for _, _, lt in props):
            return self._table(name, count, props, [0] * len(props))
        counts, k = [], self.pos
        for _, _, lt in props:
            c = int(self._tok(name, k)) if lt else 0
            counts.append(c)
            k += 1 + c if lt else 1
        try:
            return self._table(name, count, props, counts)
        except _NotUniform:
            return self._element_slow(name, count, props)

    def _tok(self, name, k):
        if k >= len(self.tokens):
            raise ValueError(f"{self.path}: PLY file ends inside element {name!r}")
        return self.tokens[k]

    def _table(self, name, count, props, counts) -> dict:
        width = sum(1 + c if lt else 1 for (_, _, lt), c in zip(props, counts))
        end = self.pos + count * width
        if end > len(self.tokens):
            if any(lt for _, _, lt in props):
                raise _NotUniform
            raise ValueError(f"{self.path}: PLY file ends inside element {name!r}")
        try:
            table = np.array(self.tokens[self.pos:end], np.float64).reshape(count, width)
        except ValueError as e:
            if any(lt for _, _, lt in props):
                raise _NotUniform from e
            raise ValueError(f"{self.path}: non-numeric value in PLY element {name!r}") from e
        cols, j = {}, 0
        for (pname, _, lt), c in zip(props, counts):
            if lt:
                if (table[:, j] != c).any():
                    raise _NotUniform
                cols[pname] = table[:, j + 1:j + 1 + c]
                j += 1 + c
            else:
                cols[pname] = table[:, j]
                j += 1
        self.pos = end
        return cols

    def _element_slow(self, name, count, props) -> dict:
        cols = {p[0]: [] for p in props}
        k = self.pos
        try:
            for _ in range(count):
                for pname, _, lt in props:
                    if lt:
                        c = int(self._tok(name, k))
                        if k + 1 + c > len(self.tokens):
                            raise ValueError(f"{self.path}: PLY file ends inside element {name!r}")
                        cols[pname].append(np.array(self.tokens[k + 1:k + 1 + c], np.float64))
                        k += 1 + c
                    else:
                        cols[pname].append(float(self._tok(name, k)))
                        k += 1
        except ValueError as e:
            if str(self.path) in str(e):
                raise
            raise ValueError(f"{self.path}: non-numeric value in PLY element {name!r}") from e
        self.pos = k
        return {pk: (np.array(v) if v and np.ndim(v[0]) == 0 else v) for pk, v in cols.items()}


class _NotUniform(Exception):
    pass


# OBJ


def _load_obj(path, data: bytes):
    verts, polys = [], []
    for lineno, raw in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        tok = raw.split()
        if not tok:
            continue
        if tok[0] == "v":
            try:
                verts.append([float(x) for x in tok[1:4]])
            except ValueError:
                raise ValueError(f"{path}:{lineno}: bad vertex line {raw.strip()!r}") from None
            if len(verts[-1]) != 3:
                raise ValueError(f"{path}:{lineno}: vertex needs 3 coordinates: {raw.strip()!r}")
        elif tok[0] == "f":
            polys.append(_obj_face(path, lineno, raw, tok[1:], len(verts)))
    v = np.array(verts, np.float64).reshape(-1, 3)
    if not polys:
        raise ValueError(f"{path}: OBJ file has no faces")
    return v, _fan(polys, path, "OBJ face")


def _obj_face(path, lineno, raw, refs, n_verts) -> np.ndarray:
    """Vertex indices (0-based) of one 'f' line: v, v/vt, v/vt/vn or v//vn; negative = from the end."""
    if len(refs) < 3:
        raise ValueError(f"{path}:{lineno}: face needs at least 3 vertices: {raw.strip()!r}")
    out = []
    for r in refs:
        try:
            i = int(r.split("/", 1)[0])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: bad face vertex {r!r} in {raw.strip()!r}") from None
        if i == 0:
            raise ValueError(f"{path}:{lineno}: face vertex index 0 (OBJ indices start at 1): {raw.strip()!r}")
        if i < 0 and -i > n_verts:
            raise ValueError(f"{path}:{lineno}: relative face vertex {i} but only {n_verts} vertices so far")
        # Positive indices may point forward; _checked bounds them once all vertices are read.
        out.append(i - 1 if i > 0 else n_verts + i)
    return np.array(out, np.int64)
