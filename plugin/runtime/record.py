"""Recording the rays a render actually traces (by kind), so benchmarks run on realistic incoherence."""
from __future__ import annotations

import io
import json

import numpy as np

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.runtime.queries import RayQueries

# Ray kinds, in the order of their codes. "first_bounce_diffuse": the ray leaving the first
# surface a camera ray hit, sampled from a diffuse lobe (the paper's most incoherent case);
# later diffuse bounces are "diffuse"; shadow rays test emitter visibility (any hit, finite tmax),
# or in a particle tracer a vertex's visibility from the sensor; "light" rays are a particle
# tracer's (ptracer): leaving an emitter, then each bounce of a light path.
KINDS = ("camera", "first_bounce_diffuse", "diffuse", "glossy", "specular", "shadow", "light")
CODE = {k: i for i, k in enumerate(KINDS)}


def bounce_kind(mi, dr, sampled_type, depth):
    """Kind codes of the rays a BSDF sample spawns: from its sampled lobe, and the bounce."""
    diffuse = mi.has_flag(sampled_type, mi.BSDFFlags.Diffuse)
    glossy = mi.has_flag(sampled_type, mi.BSDFFlags.Glossy)
    code = dr.select(glossy, CODE["glossy"], CODE["specular"])
    code = dr.select(diffuse, dr.select(depth == 0, CODE["first_bounce_diffuse"], CODE["diffuse"]), code)
    return mi.UInt32(code)


class RayRecorder:
    """Collects up to `cap` active rays per kind (origin, direction, tmax) as numpy arrays.

    Memory: 28 bytes per ray (3+3+1 float32), so the default cap of 2M per kind is at most
    56 MB per kind."""

    def __init__(self, cap: int = 2_000_000):
        self.cap = cap
        self.parts = {k: [] for k in KINDS}
        self.count = {k: 0 for k in KINDS}
        self.seen = {k: 0 for k in KINDS}

    def add(self, kind, ray, active) -> None:
        """`kind` is a kind name for the whole batch or a UInt32 array of kind codes."""
        act = np.asarray(active.numpy() if hasattr(active, "numpy") else active, bool)
        o = np.stack([np.asarray(ray.o[c]) for c in range(3)], 1).astype(np.float32)
        d = np.stack([np.asarray(ray.d[c]) for c in range(3)], 1).astype(np.float32)
        tmax = np.broadcast_to(np.asarray(ray.maxt, np.float32), act.shape)
        codes = np.full(act.shape, CODE[kind], np.uint32) if isinstance(kind, str) else np.asarray(kind, np.uint32)
        for name, code in CODE.items():
            sel = act & (codes == code)
            n = int(sel.sum())
            self.seen[name] += n
            room = self.cap - self.count[name]
            if n == 0 or room <= 0:
                continue
            idx = np.flatnonzero(sel)[:room]
            self.parts[name].append((o[idx], d[idx], tmax[idx].copy()))
            self.count[name] += len(idx)

    def arrays(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ps = self.parts[name]
        if not ps:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
        return tuple(np.concatenate([p[i] for p in ps]) for i in range(3))

    def save(self, path, vertices: np.ndarray, faces: np.ndarray, meta: dict) -> None:
        """One .npz: the scene's world-space triangles and, per kind, `<kind>_o/_d/_tmax`."""
        arrays = {"vertices": np.asarray(vertices, np.float32), "faces": np.asarray(faces, np.uint32)}
        for name in KINDS:
            o, d, t = self.arrays(name)
            arrays.update({f"{name}_o": o, f"{name}_d": d, f"{name}_tmax": t})
        meta = {**meta, "kinds": {k: {"recorded": self.count[k], "traced": self.seen[k]} for k in KINDS}}
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic.write_bytes(path, buf.getvalue())


def load(path) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """(vertices, faces, {kind: (o, d, tmax)} for kinds with rays, meta) of a recorded ray file."""
    try:
        z = np.load(path)
        meta = json.loads(bytes(z["meta"]).decode())
        # (a recording made before a kind existed has no arrays of it)
        rays = {k: (z[f"{k}_o"], z[f"{k}_d"], z[f"{k}_tmax"]) for k in KINDS
                if f"{k}_o" in z.files and len(z[f"{k}_o"])}
        return z["vertices"], z["faces"].astype(np.int64), rays, meta
    except (OSError, KeyError, ValueError) as e:
        raise ValueError(f"{path}: not a layerbvh ray recording ({e})") from None


class RecordingQueries(RayQueries):
    """Another set of queries with every active ray kept by kind in `recorder` before it is
    traced. The bounce loop labels its bounce rays (`kind`, from `bounce_kind`) only for these
    queries. Recording reads the rays on the host, so it runs in the wavefront loop."""

    symbolic = False

    def __init__(self, queries: RayQueries, recorder: RayRecorder):
        self.queries, self.recorder = queries, recorder

    def intersect(self, ray, active, hint: str = "camera", kind=None):
        self.recorder.add(hint if kind is None else kind, ray, active)
        return self.queries.intersect(ray, active, hint=hint)

    def occluded(self, ray, active):
        self.recorder.add("shadow", ray, active)
        return self.queries.occluded(ray, active)
