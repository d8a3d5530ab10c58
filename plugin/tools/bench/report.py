"""Turn benchmark JSON (bench_traversal.py, bench_scaling.py) into BENCHMARKS.md with its plots, and the headline of
docs/results.md."""
from __future__ import annotations

import argparse
import io
import json
import sys
from collections import defaultdict
from pathlib import Path

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT
from layerbvh_mitsuba.tools.bench import traversal_figures as btf
from layerbvh_mitsuba.tools.bench import gpu_report
from layerbvh_mitsuba.tools.bench.locality import benchmarks_section, merge_documents, write_figures

MIB = 1 << 20
LAYER_MODES = ("layer_sorted", "layer_unsorted")
STAGES = ("sort", "treelet", "leaf", "other")


def load(path) -> dict:
    try:
        doc = json.loads(Path(path).read_text())
        doc["results"]  # noqa: B018  (a benchmark JSON has results)
        return doc
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"report: {path}: not a benchmark JSON ({e})")


def ray_sets(rows: list[dict]) -> dict:
    """(mesh, rays) -> rows, in the order they were measured."""
    out = defaultdict(list)
    for r in rows:
        out[(r["mesh"], r["rays"])].append(r)
    return out


def best(rows: list[dict], mode: str, branching: int | None = None) -> dict | None:
    """The fastest row of `mode` (of one branching if given; rows from before branching was an
    axis are binary)."""
    cands = [r for r in rows if r["mode"] == mode and (branching is None or _k(r) == branching)]
    return max(cands, key=lambda r: r["mrays_s"]) if cands else None


def _k(r: dict) -> int | None:
    return None if r["mode"] == "embree" else r.get("branching") or 2


def layout_of(r: dict) -> str:
    """A row's layout as tables show it: K (children per node) and treelet height."""
    return f"K={_k(r)} h={r['treelet_height']}"


def work_memory(r: dict) -> float | None:
    """BVH + ray state + hits + stacks and queues, in bytes (what the memory target counts)."""
    return None if r["bvh_bytes"] is None or r["work_bytes"] is None else r["bvh_bytes"] + r["work_bytes"]


def _f(x, spec=".2f"):
    return "–" if x is None else format(x, spec)


def headline_rows(rows: list[dict]) -> list[dict]:
    out = []
    for (mesh, kind), rs in ray_sets(rows).items():
        emb, per, srt, auto = best(rs, "embree"), best(rs, "per_ray"), best(rs, "layer_sorted"), best(rs, "auto")
        if not (emb and per and srt):
            continue
        mem_s, mem_p = work_memory(srt), work_memory(per)
        binary = best(rs, "per_ray", 2)
        out.append({"mesh": mesh, "triangles": per["triangles"], "rays": kind, "query": per.get("query", "closest_hit"),
                    "ray_count": per["ray_count"], "embree": emb["mrays_s"], "per_ray": per["mrays_s"],
                    "per_ray_h": per["treelet_height"], "per_ray_layout": layout_of(per),
                    "binary_per_ray": binary and binary["mrays_s"],
                    "sorted": srt["mrays_s"], "sorted_h": srt["treelet_height"], "sorted_layout": layout_of(srt),
                    "sorted_vs_per_ray": srt["mrays_s"] / per["mrays_s"],
                    "sorted_vs_embree": srt["mrays_s"] / emb["mrays_s"],
                    "per_ray_vs_embree": per["mrays_s"] / emb["mrays_s"],
                    "memory_vs_per_ray": mem_s / mem_p if mem_s and mem_p else None,
                    "auto": auto and auto["mrays_s"], "auto_choice": auto and btf.mode_label(auto),
                    "auto_vs_best_of_two": auto and auto.get("ratio_best_of_two")})
    return out


def headline_table(rows: list[dict]) -> str:
    lines = ["| scene / mesh | triangles | rays | query | Embree Mrays/s | per_ray (best K, h) "
             "| layer_sorted (best K, h) | sorted × per_ray | sorted × Embree | per_ray × Embree "
             "| binary per_ray × Embree | sorted memory × per_ray | auto (its choice) | auto × faster of the two |",
             "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for h in headline_rows(rows):
        binary = h["binary_per_ray"] and h["binary_per_ray"] / h["embree"]
        lines.append(f"| {h['mesh']} | {h['triangles']:,} | {h['rays']} ({h['ray_count']:,}) "
                     f"| {h['query'].replace('_', '-')} | {h['embree']:.2f} "
                     f"| {h['per_ray']:.2f} ({h['per_ray_layout']}) "
                     f"| {h['sorted']:.2f} ({h['sorted_layout']}) | {h['sorted_vs_per_ray']:.2f} "
                     f"| {h['sorted_vs_embree']:.2f} | {h['per_ray_vs_embree']:.2f} | {_f(binary)} "
                     f"| {_f(h['memory_vs_per_ray'])} "
                     f"| {_f(h['auto'])} {h['auto_choice'] or ''} | {_f(h['auto_vs_best_of_two'])} |")
    return "\n".join(lines)


def branching_table(rows: list[dict]) -> str:
    """Per ray set and branching: per_ray against Embree and against the binary per_ray, and
    layer_sorted against per_ray on the same layout, at each treelet height."""
    ks = sorted({_k(r) for r in rows if _k(r)})
    hs = sorted({r["treelet_height"] for r in rows if r["treelet_height"] is not None})
    lines = ["| scene / mesh | rays | K | per_ray Mrays/s (best h) | × Embree | × binary per_ray | inner/ray "
             "| box tests/ray | iters/ray | " + " | ".join(f"sorted × per_ray h={h}" for h in hs) + " | BVH MiB |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(hs) + "---:|"]
    for (mesh, kind), rs in ray_sets(rows).items():
        emb, binary = best(rs, "embree"), best(rs, "per_ray", 2)
        for k in ks:
            per = best(rs, "per_ray", k)
            if not per or not emb:
                continue
            cells = []
            for h in hs:
                s = [r for r in rs if r["mode"] == "layer_sorted" and _k(r) == k and r["treelet_height"] == h]
                cells.append(_f(s[0].get("ratio_per_ray_same_h")) if s else "–")
            lines.append(f"| {mesh} | {kind} | {k} | {per['mrays_s']:.2f} (h={per['treelet_height']}) "
                         f"| {per['mrays_s'] / emb['mrays_s']:.2f} "
                         f"| {_f(binary and per['mrays_s'] / binary['mrays_s'])} "
                         f"| {_f(per['inner_per_ray'], '.1f')} | {_f(per.get('box_tests_per_ray'), '.1f')} "
                         f"| {_f(per.get('iterations_per_ray'), '.1f')} | " + " | ".join(cells)
                         + f" | {_f(per['bvh_bytes'] and per['bvh_bytes'] / MIB, '.1f')} |")
    return "\n".join(lines)


def full_table(rs: list[dict]) -> str:
    lines = ["| mode | K | h | Mrays/s | runs min–max | × per_ray | × Embree | inner/ray | leaves/ray | tris/ray "
             "| steps | sort s | treelet s | leaf s | other s | BVH MiB | work MiB | peak RSS +MiB |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rs:
        ts = r.get("time_split_s") or {}
        lines.append(
            f"| {btf.mode_label(r)} | {_f(_k(r), 'd')} | {_f(r['treelet_height'], 'd')} | {r['mrays_s']:.2f} "
            f"| {min(r['runs']):.2f}–{max(r['runs']):.2f} | {r['ratio_per_ray']:.2f} | {r['ratio_embree']:.2f} "
            f"| {_f(r['inner_per_ray'], '.1f')} | {_f(r['leaves_per_ray'])} | {_f(r['tris_per_ray'], '.1f')} "
            f"| {_f(r['steps'], 'd')} | " + " | ".join(_f(ts.get(k), '.3f') for k in STAGES)
            + f" | {_f(r['bvh_bytes'] and r['bvh_bytes'] / MIB, '.1f')} "
            f"| {_f(r['work_bytes'] and r['work_bytes'] / MIB, '.1f')} "
            f"| {_f(r.get('rss_extra_bytes') and r['rss_extra_bytes'] / MIB, '.0f')} |")
    return "\n".join(lines)


def build_table(rows: list[dict]) -> str:
    seen, lines = set(), ["| mesh | triangles | K | treelet h | layerbvh build s (collapse included) | Mtris/s "
                          "| Embree (Mitsuba scene) build s |",
                          "|---|---:|---:|---:|---:|---:|---:|"]
    for (mesh, _), rs in ray_sets(rows).items():
        emb = best(rs, "embree")
        for r in rs:
            key = (mesh, _k(r), r["treelet_height"])
            if r["mode"] in LAYER_MODES and key not in seen:
                seen.add(key)
                lines.append(f"| {mesh} | {r['triangles']:,} | {_k(r)} | {r['treelet_height']} | {r['build_s']:.2f} "
                             f"| {r['triangles'] / r['build_s'] / 1e6:.2f} | {_f(emb and emb['build_s'])} |")
    return "\n".join(lines)


# -- plots ------------------------------------------------------------------------------------------


def _plt():
    import matplotlib  # local: matplotlib loads only when a plot is drawn
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # local: matplotlib loads only when a plot is drawn
    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    _plt().close(fig)
    return buf.getvalue()


def plot_heights(rows: list[dict]) -> bytes:
    """Mrays/s against treelet height, one panel per ray set; per_ray and Embree as flat lines."""
    plt = _plt()
    sets = list(ray_sets(rows).items())
    cols = min(4, len(sets))
    nrows = (len(sets) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.3 * nrows), squeeze=False)
    for ax, ((mesh, kind), rs) in zip(axes.flat, sets):
        ks = sorted({_k(r) for r in rs if _k(r)})
        for k, color in zip(ks, ("C0", "C1", "C2", "C3")):
            for mode, style in (("layer_sorted", "o-"), ("layer_unsorted", "s--"), ("per_ray", "^:")):
                pts = sorted((r["treelet_height"], r["mrays_s"]) for r in rs if r["mode"] == mode and _k(r) == k)
                if len(pts) > 1:
                    ax.plot(*zip(*pts), style, color=color, label=f"{mode} K={k}")
                elif pts:  # one layout only: a flat reference line
                    ax.axhline(pts[0][1], ls="-", color=color, label=f"{mode} K={k}")
        r = best(rs, "embree")
        if r:
            ax.axhline(r["mrays_s"], ls=":", color="grey", label="embree")
        ax.set_title(f"{mesh}: {kind}", fontsize=9)
        ax.set_xlabel("treelet height")
        ax.set_ylabel("Mrays/s")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(sets):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


def plot_time_split(rows: list[dict]) -> bytes:
    """Seconds per stage (sort, treelet traversal, leaf tests, other host work) for per_ray and the
    best height of each layer mode, per ray set."""
    plt = _plt()
    bars, labels = [], []
    for (mesh, kind), rs in ray_sets(rows).items():
        for mode in ("per_ray",) + LAYER_MODES:
            r = best(rs, mode)
            if r and r.get("time_split_s"):
                bars.append([r["time_split_s"][k] * 1e3 / (r["ray_count"] / 1e6) for k in STAGES])
                labels.append(f"{mesh} {kind}\n{mode} {layout_of(r)}")
    fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(bars)), 4.8))
    bottom = [0.0] * len(bars)
    for i, stage in enumerate(STAGES):
        vals = [b[i] for b in bars]
        ax.bar(range(len(bars)), vals, bottom=bottom, label=stage)
        bottom = [x + y for x, y in zip(bottom, vals)]
    ax.set_xticks(range(len(bars)), labels, rotation=90, fontsize=6)
    ax.set_ylabel("ms per million rays")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return _png(fig)


def scaling_series(rows: list[dict]) -> dict:
    """label -> sorted [(triangles, row)]"""
    out = defaultdict(list)
    for r in rows:
        label = r["mode"] if r["treelet_height"] is None else f"{r['mode']} {layout_of(r)}"
        out[label].append((r["triangles"], r))
    return {k: sorted(v, key=lambda p: p[0]) for k, v in out.items()}


def plot_scaling(rows: list[dict]) -> bytes:
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for label, pts in scaling_series(rows).items():
        x = [p[0] for p in pts]
        axes[0].plot(x, [p[1]["ray_count"] / p[1]["mrays_s"] / 1e6 for p in pts], "o-", label=label)
        if label != "embree":
            axes[1].plot(x, [work_memory(p[1]) / MIB for p in pts], "o-", label=label)
            if label.startswith("per_ray"):
                axes[2].plot(x, [p[1]["build_s"] for p in pts], "o-", label=f"layerbvh build ({label.split()[-1]})")
        else:
            axes[2].plot(x, [p[1]["build_s"] for p in pts], "s--", label="Embree (Mitsuba scene)")
    titles = ("trace time (s) for the ray set", "BVH + work memory (MiB)", "build time (s)")
    for ax, t in zip(axes, titles):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("triangles")
        ax.set_title(t, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def scaling_table(rows: list[dict]) -> str:
    series = scaling_series(rows)
    labels = list(series)
    sizes = sorted({p[0] for pts in series.values() for p in pts})
    lines = ["| triangles | " + " | ".join(f"{lb} Mrays/s" for lb in labels) + " | "
             + " | ".join(f"{lb} MiB" for lb in labels if lb != "embree") + " | build s |",
             "|---:|" + "---:|" * (2 * len(labels))]
    for n in sizes:
        by = {lb: dict(pts).get(n) for lb, pts in series.items()}
        per = next((by[lb] for lb in labels if lb.startswith("per_ray") and by[lb]), None)
        lines.append(f"| {n:,} | " + " | ".join(_f(by[lb] and by[lb]["mrays_s"]) for lb in labels) + " | "
                     + " | ".join(_f(by[lb] and work_memory(by[lb]) / MIB, ".0f") for lb in labels if lb != "embree")
                     + f" | {_f(per and per['build_s'])} |")
    return "\n".join(lines)


# -- the document -----------------------------------------------------------------------------------


def machine_line(doc: dict) -> str:
    m, v = doc["machine"], doc["versions"]
    return (f"{m['cpu']}, {m['cores']} cores ({m['drjit_threads']} Dr.Jit threads), {m['os']}; "
            + ", ".join(f"{k} {x}" for k, x in v.items()))


def converge_section(dirs: list[Path], out_dir: Path) -> list[str]:
    """Each `layerbvh converge` output folder: its command line settings, table and plot."""
    parts = ["## Error against run time (`layerbvh converge`)", ""]
    for d in dirs:
        doc = json.loads((d / "convergence.json").read_text())
        table = (d / "convergence.md").read_text().split("\n", 2)[2].strip()  # drop the file's own title
        rel = d.resolve()
        rel = rel.relative_to(out_dir.resolve()) if rel.is_relative_to(out_dir.resolve()) else rel
        configs = ",".join(c["name"] for c in doc["configs"])
        parts += [f"### {Path(doc['scene']).name}", "",
                  f"`.venv/bin/layerbvh converge {doc['scene']} --budget {doc['budget_s']:g} --res "
                  f"{doc['resolution'][0]} {doc['resolution'][1]} --ref-spp {doc['reference']['spp']} "
                  f"--configs {configs} --out {rel}`", "", table, "", f"![convergence]({rel}/convergence.png)", ""]
    return parts


LOCALITY_SECTION = "locality"  # BENCHMARKS.md's markers around the locality section


# Sections other commands write (scripts/check_model_cachegrind.py --report): kept as they are.
KEPT_SECTIONS = ("cachegrind",)


def kept_section(path: Path, name: str) -> str | None:
    """The section `name` of the document at `path`, markers included (None: not there)."""
    body = atomic.read_section(path, name)
    return None if body is None else "\n".join(atomic.marked_lines(name, body))


def locality_block(doc: dict, fig_dir: str) -> list[str]:
    """The locality section between its markers."""
    return atomic.marked_lines(LOCALITY_SECTION, benchmarks_section(doc, fig_dir))


def document(bench: list[dict], scaling: dict | None, fig_dir: str, converge: list[str] | None = None,
             locality: list[str] | None = None, gpu: list[str] | None = None, kept: list[str] | None = None) -> str:
    rows = [r for d in bench for r in d["results"]]
    parts = ["# Benchmarks", "",
             "Generated by `scripts/report.py` from the JSON of `scripts/bench_traversal.py` and "
             "`scripts/bench_scaling.py`; every number below comes from the commands listed, run side by side "
             "in one process (ratios are taken within one run; absolute numbers on these shared machines vary "
             "by ±30%). Mrays/s is the median of the timed runs after one warm-up; Embree is stock Mitsuba's "
             "`ray_intersect_preliminary` / `ray_test` on the same triangles. Memory: BVH bytes plus the "
             "traversal's work arrays (ray state, hits, stacks, queues), and the process's peak RSS increase "
             "while the configuration ran (after Dr.Jit's allocation cache was released).", ""]
    for d in bench + ([scaling] if scaling else []):
        parts += [f"- `{d['command']}`", f"  ({machine_line(d)})"]
    parts += ["", "## Headline", "",
              "Best layout (branching K, treelet height h) of `layer_sorted` per ray set, against the best layout of "
              "`per_ray` (the same BVH, one kernel, a per-ray stack), the binary `per_ray` (K=2, the paper's tree) and "
              "Embree. `auto` runs on the h=4 layout (the integrator's "
              "default) and is compared with the faster (by median) of `per_ray` and `layer_sorted` on that layout: "
              "the median over rounds of auto's throughput over that mode's in the same round (the three run back "
              "to back).", "",
              headline_table(rows), "",
              f"![throughput against treelet height]({fig_dir}/throughput_vs_height.png)", "",
              "## Branching", "",
              "Per ray set and branching K (children per node: 2 is the binary BVH, 4 and 8 are collapsed from it "
              "with leaves of 2): `per_ray` at its best height against Embree and the binary `per_ray`; the work per "
              "ray (inner-node visits are the dependent node loads; each visit tests K boxes; loop iterations); and "
              "`layer_sorted` against `per_ray` on the same layout at each treelet height (h counts binary levels: "
              "a treelet holds ceil(h / log2 K) levels of the K-wide tree).", "",
              branching_table(rows), "",
              "## Time per stage", "",
              "Sort: counting sort and permutation between wavefront steps; treelet / leaf: the traversal kernel's "
              "time, split by the share of loop iterations spent on triangles (an estimate); other: host work "
              "between steps (compaction, bookkeeping).", "",
              f"![time per stage]({fig_dir}/time_split.png)", "", "## Build", "", build_table(rows), ""]
    if scaling:
        parts += ["## Scaling with scene size", "",
                  "The `spheres` stress scene (scripts/gen_stress.py) from 10k triangles up, random rays "
                  "through its bounding box.", "", scaling_table(scaling["results"]), "",
                  f"![scaling]({fig_dir}/scaling.png)", ""]
    parts += converge or []
    parts += locality or []
    parts += gpu or []
    parts += kept or []
    parts += ["## Every ray set", ""]
    for (mesh, kind), rs in ray_sets(rows).items():
        r0 = rs[0]
        parts += [f"### {mesh} ({r0['triangles']:,} triangles): {kind} rays, "
                  f"{r0.get('query', 'closest_hit').replace('_', '-')}", "",
                  f"{r0['ray_count']:,} rays, {r0.get('source', 'generated')}; "
                  f"{100 * best(rs, 'per_ray')['hit_fraction']:.1f}% hit.", "", full_table(rs), ""]
    return "\n".join(parts)


def readme_headline(bench: list[dict]) -> str:
    rows = [r for d in bench for r in d["results"]]
    return ("Headline ratios from [BENCHMARKS.md](BENCHMARKS.md) (generated by `scripts/report.py`; commands and "
            "machine there):\n\n" + headline_table(rows))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--bench", action="append", default=[], help="bench_traversal.py --json output (repeatable)")
    p.add_argument("--scaling", help="bench_scaling.py --json output")
    p.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    p.add_argument("--figures", default=str(ROOT / "docs" / "bench"), help="folder for the plots")
    p.add_argument("--converge", action="append", default=[], help="a `layerbvh converge` output folder (repeatable)")
    p.add_argument("--readme", action="store_true", help="also splice the headline into docs/results.md")
    p.add_argument("--locality", action="append", default=[],
                   help="a locality.json (`layerbvh locality`, or a locality sweep's merged one; repeatable, merged): "
                        "its section; without --bench only that section of the existing document is replaced")
    p.add_argument("--gpu", default=str(gpu_report.DEFAULT_FOLDER),
                   help="a GPU check's folder (gpu_report.py) for the GPU section (default %(default)s, if it exists)")
    args = p.parse_args(argv)
    if not args.bench and not args.locality:
        p.error("give --bench (the whole document) or --locality (its locality section)")
    figs, out = Path(args.figures), Path(args.out)
    rel = figs.resolve().relative_to(out.resolve().parent) if figs.resolve().is_relative_to(
        out.resolve().parent) else figs.resolve()
    loc = None
    if args.locality:
        doc = merge_documents([load(f) for f in args.locality])
        write_figures(doc, figs)
        loc = locality_block(doc, str(rel))
        if not args.bench:
            atomic.splice_section(out, LOCALITY_SECTION, "\n".join(loc[1:-2]))
            print(f"replaced the locality section of {out}; plots in {figs}")
            return 0
    bench = [load(b) for b in args.bench]
    scaling = load(args.scaling) if args.scaling else None
    rows = [r for d in bench for r in d["results"]]
    atomic.write_bytes(figs / "throughput_vs_height.png", plot_heights(rows))
    atomic.write_bytes(figs / "time_split.png", plot_time_split(rows))
    if scaling:
        atomic.write_bytes(figs / "scaling.png", plot_scaling(scaling["results"]))
    conv = converge_section([Path(c) for c in args.converge], out.parent) if args.converge else None
    gpu = gpu_report.block(Path(args.gpu)) if Path(args.gpu).is_dir() else None
    kept = [block for name in KEPT_SECTIONS if (block := kept_section(out, name))]
    atomic.write_text(out, document(bench, scaling, str(rel), conv, loc, gpu, kept))
    if args.readme:
        atomic.splice_section(ROOT / "docs" / "results.md", "bench_headline", readme_headline(bench))
    print(f"wrote {out} and plots in {figs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
