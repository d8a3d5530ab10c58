"""The GPU check of the locality model, the half that runs here: record a scene's rays, replay them through the model
for the GPU's preset, and write what the device half (scripts/gpu_check_device.py) needs: the rays, the triangles,
the replay's hits and the model's prediction."""
from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np

import layerbvh
from layerbvh import LocalitySettings, RaySet, measure, preset as named_preset, replay
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import use_variant
from layerbvh_mitsuba.tools.bench.locality import rows_of
from layerbvh_mitsuba.tools.bench.record_rays import cached_recording

KINDS = ("camera", "first_bounce_diffuse", "diffuse", "shadow")
RAYS_PER_KIND = 200_000   # the device half must fit the device tool's 64 MiB carry with the drjit wheel
MODES = ("per_ray", "layer_sorted")
# (branching, treelet height) pairs timed on the device: the paper's binary tree at the default
# height, the default 4-wide tree there, and the 4-wide tree at height 12, where the model has the
# sorted path's total DRAM bytes below per_ray's (PERFORMANCE.md entry 38).
CONFIGS = ((2, 8), (4, 8), (4, 12))


def parse_config(text: str) -> tuple[int, int]:
    """'K:H' -> (branching, treelet height)."""
    try:
        k, h = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a config is BRANCHING:HEIGHT, for example 4:8; got {text!r}") from None
    return k, h


def prepare(scene: str, out: Path, preset: str, configs, res, spp: int, rays_per_kind: int) -> dict:
    """Write out/rays.npz (triangles; per kind the rays and the replay's prim and t) and
    out/model.json (the model's per_ray and layer_sorted rows for `preset`, per (branching, treelet
    height) of `configs`); returns model.json."""

    mi = use_variant("llvm_ad_rgb")
    v, f, rays, meta = cached_recording(mi, scene, res, spp, 0, rays_per_kind)
    sets = [RaySet(k, *rays[k], any_hit=k == "shadow") for k in KINDS if k in rays]
    rows, checks = [], []
    for k in sorted({k for k, _ in configs}):
        heights = tuple(sorted({h for kk, h in configs if kk == k}))
        run = measure(v, f, sets, LocalitySettings(modes=MODES, presets=(preset,), treelet_heights=heights,
                                                   branching=k), None)
        rows += [r.as_dict() for r in rows_of(run.as_dict())]
        checks += run.checks
    arrays = {"vertices": np.asarray(v, np.float32), "faces": np.asarray(f, np.int64)}
    # Hits are the same on every tree and mode (docs/method.md: exactness), so one replay gives them all.
    bvh = layerbvh.build(v, f, treelet_height=configs[0][1], branching=configs[0][0],
                         batch_rays=max(len(s.o) for s in sets))
    for s in sets:  # the replay's hits: what the LLVM kernel returns, bit for bit (checked in measure)
        rep = replay(bvh.layout, s.o, s.d, s.tmax, "per_ray", s.any_hit, 32, named_preset(preset))
        arrays.update({f"{s.kind}_o": s.o, f"{s.kind}_d": s.d, f"{s.kind}_tmax": s.tmax, f"{s.kind}_prim": rep.prim,
                       f"{s.kind}_t": rep.t})
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic.write_bytes(out / "rays.npz", buf.getvalue())
    model = {"scene": str(scene), "preset": named_preset(preset).as_dict(), "configs": [list(c) for c in configs],
             "checks": checks, "rows": rows, "kinds": [s.kind for s in sets],
             "recording": {"resolution": list(res), "spp": spp, "rays_per_kind": rays_per_kind}}
    atomic.write_text(out / "model.json", json.dumps(model, indent=1))
    return model


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scene", default="scenes/paper_mix.xml")
    p.add_argument("--out", default="out/gpu_check")
    p.add_argument("--preset", default="h200", help="the GPU's preset (default %(default)s)")
    p.add_argument("--configs", type=parse_config, nargs="+", default=CONFIGS, metavar="K:H",
                   help="branching:treelet height pairs to time (default: 2:8 4:8 4:12)")
    p.add_argument("--res", type=int, nargs=2, default=(512, 512))
    p.add_argument("--spp", type=int, default=1)
    p.add_argument("--rays", type=int, default=RAYS_PER_KIND, help="rays per kind (default %(default)s)")
    args = p.parse_args(argv)
    model = prepare(args.scene, Path(args.out), args.preset, tuple(args.configs), tuple(args.res), args.spp, args.rays)
    exact = all(c["exact"] for c in model["checks"])
    print(f"wrote {args.out}/rays.npz and model.json ({', '.join(model['kinds'])}; trace "
          f"{'exact' if exact else 'NOT exact'} against the LLVM kernel)")
    return 0 if exact else 1


if __name__ == "__main__":
    sys.exit(main())
