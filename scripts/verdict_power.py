"""The verdict's false-alarm rate and detection rate, measured over seeds (issue 55, item 4).

For each scene at its own max_depth and the size below, and each bias (every diffuse
reflectance of ours' copy of the scene scaled by FACTOR; 1.0 is the unmodified scene), the
verdict of `layerbvh compare` (testing.verdict_vs_stock, the same code) is taken at compare seeds
0..N-1: a seed moves the same-seed renders and the independent-seed renders alike
(verdict.independent_seeds), so the verdicts are independent draws. Each verdict is one JSON
record in RESULTS, keyed by scene, factor and seed: a run can be stopped at any time and goes on
from there (`--seeds` and `--factors` take slices; run it in the background).

  .venv/bin/python scripts/verdict_power.py [--scenes NAME ...] [--factors F ...] [--seeds N] [--quick]
  .venv/bin/python scripts/verdict_power.py --table     # the table (docs/verdict_power.md) and plot from RESULTS
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "verdict_power"
RESULTS = OUT / "results.json"
# The scenes: (file, spp, film (W, H)); each at its own max_depth. staircase2 and veach-mis are
# Bitterli's interiors, whose same-seed paths diverge at depth (staircase2) or which hold many
# shapes and lights (veach-mis); bunny_box at the main job's settings; paper_mix (glass, mirrors).
SCENES = {
    "bunny_box": ("scenes/bunny_box.xml", 16, (128, 128)),
    "staircase2": ("scenes/staircase2/scene.xml", 16, (256, 144)),
    "veach-mis": ("scenes/veach-mis/scene.xml", 16, (256, 144)),
    "paper_mix": ("scenes/paper_mix.xml", 16, (128, 128)),
}
FACTORS = (1.0, 1.005, 1.01, 1.02, 1.03, 1.05)
SEEDS = 20


def _key(scene: str, factor: float, seed: int) -> str:
    return f"{scene}|{factor:g}|{seed}"


def _load() -> dict:
    return json.loads(RESULTS.read_text()) if RESULTS.exists() else {"meta": {}, "runs": {}}


def _save(doc: dict) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = RESULTS.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=1, sort_keys=True))
    tmp.replace(RESULTS)  # write, then rename: a stopped run leaves the last whole file


def run(scenes: list[str], factors: list[float], seeds: int) -> None:
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import layerbvh
    from layerbvh_mitsuba import testing
    doc = _load()
    doc["meta"].update(cpu=layerbvh.cpu_model(), llvm_lanes=layerbvh.llvm_vector_width(), machine=platform.machine())
    for name in scenes:
        path, spp, res = SCENES[name]
        for factor in factors:
            for seed in range(seeds):
                key = _key(name, factor, seed)
                if key in doc["runs"]:
                    continue
                t0 = time.perf_counter()
                v = testing.verdict_vs_stock(ROOT / path, spp=spp, res=res, seed=seed, traversal="auto",
                                             ours_modify=None if factor == 1.0 else testing.scaled_reflectances(factor))
                fam = v.family
                doc["runs"][key] = {"scene": name, "factor": factor, "seed": seed, "label": v.label,
                                    "same_seed_passed": bool(v.same_seed["passed"]),
                                    "rejected": bool(fam.rejected) if fam else None,
                                    "mde": v.mde(), "tests": sum(fam.counts.values()) if fam else 0,
                                    "strongest": fam.rejections[0].describe() if fam and fam.rejections else None,
                                    "seconds": round(time.perf_counter() - t0, 2),
                                    "llvm_lanes": layerbvh.llvm_vector_width()}
                _save(doc)
                print(f"{key}: {v.label} ({doc['runs'][key]['seconds']} s)", flush=True)


def table() -> str:
    doc = _load()
    runs = list(doc["runs"].values())
    names = [n for n in SCENES if any(r["scene"] == n for r in runs)]
    factors = sorted({r["factor"] for r in runs})
    lanes = {f: sorted({r.get("llvm_lanes", "?") for r in runs if r["factor"] == f}) for f in factors}
    by = "; ".join(f"x{f:g}: {', '.join(map(str, lanes[f]))} lanes" for f in factors)
    lines = [f"Measured on {doc['meta'].get('cpu', '?')}, Dr.Jit LLVM at the lanes each factor's runs had "
             f"({by}: 16 is AVX-512, 8 AVX2); `.venv/bin/python scripts/verdict_power.py` "
             f"(docs/verdict_power/results.json).", "",
             "Share of seeds whose verdict is \"differs\" (factor 1: the false-alarm rate; else the detection rate), "
             "and the median MDE of the image mean stated by the unmodified scene's verdicts:", "",
             "| scene | settings | " + " | ".join(f"x{f:g}" for f in factors) + " | median MDE (image) |",
             "|---|---|" + "---|" * (len(factors) + 1)]
    for n in names:
        _, spp, (w, h) = SCENES[n]
        cells = []
        for f in factors:
            rs = [r for r in runs if r["scene"] == n and r["factor"] == f]
            cells.append(f"{sum(r['label'] == 'differs beyond noise' for r in rs)}/{len(rs)}" if rs else "-")
        mdes = sorted(r["mde"]["image"] for r in runs if r["scene"] == n and r["factor"] == 1.0
                      and r.get("mde") and r["mde"].get("image") is not None)
        med = f"{100 * mdes[len(mdes) // 2]:.2g}%" if mdes else "-"
        lines.append(f"| {n} | {w}x{h}, {spp} spp | " + " | ".join(cells) + f" | {med} |")
    text = "\n".join(lines) + "\n"
    tmp = OUT / "table.md.tmp"
    tmp.write_text("# The verdict's false alarms and detections (scripts/verdict_power.py)\n\n" + text)
    tmp.replace(OUT / "table.md")
    _plot(runs, names, factors)
    return text


def _plot(runs, names, factors) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for n in names:
        xs, ys = [], []
        for f in factors:
            rs = [r for r in runs if r["scene"] == n and r["factor"] == f]
            if rs:
                xs.append(100 * (f - 1))
                ys.append(sum(r["label"] == "differs beyond noise" for r in rs) / len(rs))
        ax.plot(xs, ys, marker="o", label=n)
    ax.set_xlabel("bias: every reflectance scaled by 1 + x/100 (x in %)")
    ax.set_ylabel('share of seeds: "differs"')
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = OUT / "power.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(OUT / "power.png")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--factors", nargs="+", type=float, default=list(FACTORS))
    ap.add_argument("--seeds", type=int, default=SEEDS)
    ap.add_argument("--quick", action="store_true", help="3 seeds of x1 and x1.01 (a smoke run)")
    ap.add_argument("--table", action="store_true", help="only the table and plot from the stored results")
    a = ap.parse_args(argv)
    if not a.table:
        if a.quick:
            a.factors, a.seeds = [1.0, 1.01], 3
        run(a.scenes, a.factors, a.seeds)
    print(table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
