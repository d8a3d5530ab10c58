"""`layerbvh locality`: a scene's recorded rays replayed through the locality model (layerbvh.locality) by kind,
mode, warp width, preset and treelet height; DIR/locality.json, locality.png and summary.md."""
from __future__ import annotations

import io
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

import layerbvh
from layerbvh import (
    PRESETS,
    TAIL_STEPS,
    CacheLevel,
    LocalityRow,
    LocalitySettings,
    Preset,
    RaySet,
    at_headline,
    cpu_model,
    headline_config,
    llvm_vector_width,
    measure,
    preset as named_preset,
    preset_verdict,
)
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import load_scene
from layerbvh_mitsuba.ab.report import json_safe
from layerbvh_mitsuba.runtime.record import KINDS
from layerbvh_mitsuba.tools.bench import model_checked
from layerbvh_mitsuba.tools.bench.record_rays import cached_recording

OUTPUT_MARKER = "locality.json"   # the file that makes a folder a locality output
DEFAULT_KINDS = ("camera", "first_bounce_diffuse", "diffuse", "shadow")
DEFAULT_PRESETS = ("gtx965m", "h200", "cpu")
DEFAULT_SPP = 1          # one sample per pixel at the scene's resolution: 0.1-1M rays per kind
DEFAULT_CAP = 1_000_000  # rays recorded per kind at most
ANY_HIT_KINDS = ("shadow",)


@dataclass(frozen=True)
class LocalityRequest:
    """What `layerbvh locality` (and the sweep's locality job) runs on one scene, parsed once."""
    scene: str
    res: tuple | None
    spp: int
    seed: int
    kinds: tuple
    warps: tuple | None          # None: each preset's own width (32 on the GPUs, the CPU's SIMD lanes)
    presets: tuple
    treelet_heights: tuple
    modes: tuple
    leaf_size: int | None          # None: the branching's default (inputs.default_leaf_size)
    sample: int | None
    cap: int
    check: bool = True
    segments: tuple | None = None  # None: each preset's own transaction size
    branching: int = layerbvh.DEFAULT_BRANCHING  # the tree a render of the scene gets, unless asked
    tail_steps: int = TAIL_STEPS  # the layer modes' step cap (wavefront.takes_tail), unless asked


def parse_list(text: str, what: str, choices=None, kind=str) -> tuple:
    """A comma list of `what` (UserError-ready ValueError naming the bad item)."""
    items = [x.strip() for x in str(text).split(",") if x.strip()]
    if not items:
        raise ValueError(f"--{what} needs at least one value")
    out = []
    for x in items:
        try:
            v = kind(x)
        except ValueError:
            raise ValueError(f"--{what}: {x!r} is not a {kind.__name__}") from None
        if choices is not None and v not in choices:
            raise ValueError(f"--{what}: unknown {x!r}; one of {', '.join(map(str, choices))}")
        out.append(v)
    return tuple(dict.fromkeys(out))


def request_from_args(args) -> LocalityRequest:
    """The command's options as a LocalityRequest; ValueError names the bad option."""
    kinds = parse_list(args.rays, "rays", KINDS)
    presets = parse_list(args.preset, "preset", tuple(PRESETS))
    warps = None if args.warp is None else parse_list(args.warp, "warp", kind=int)
    if warps is not None and any(w < 1 or w > 64 for w in warps):
        raise ValueError(f"--warp: widths must be in [1, 64], got {','.join(map(str, warps))}")
    heights = parse_list(args.treelet_heights, "treelet-heights", kind=int)
    for h in heights:
        layerbvh.check_param("treelet_height", h)
    modes = parse_list(args.modes, "modes", layerbvh.MODES)
    segments = None if getattr(args, "segment", None) is None else parse_list(args.segment, "segment", kind=int)
    if segments is not None and any(x < 1 or x & (x - 1) for x in segments):
        raise ValueError(f"--segment: sizes must be powers of two, got {','.join(map(str, segments))}")
    if args.sample is not None and args.sample < 1:
        raise ValueError(f"--sample must be >= 1, got {args.sample}")
    if args.spp is not None and args.spp < 1:
        raise ValueError(f"--spp must be >= 1, got {args.spp}")
    return LocalityRequest(scene=args.scene, res=tuple(args.res) if args.res else None, spp=args.spp or DEFAULT_SPP,
                           seed=args.seed, kinds=kinds, warps=warps, presets=presets, treelet_heights=heights,
                           modes=modes, leaf_size=None if args.leaf_size is None else
                           layerbvh.check_param("leaf_size", args.leaf_size),
                           sample=args.sample, cap=args.cap, check=not args.no_check, segments=segments,
                           branching=layerbvh.check_param("branching", getattr(args, "branching", None) or
                                                          layerbvh.DEFAULT_BRANCHING),
                           tail_steps=layerbvh.check_param("tail_steps", getattr(args, "tail_steps", None) or
                                                           TAIL_STEPS))


def measure_scene(mi, req: LocalityRequest, progress: bool = True) -> dict:
    """Record the scene's rays (cached), replay every configuration, and return locality.json's
    document: {"results": [row, ...], "checks", "verdict", "scene", "presets", ...}."""

    res = req.res
    if res is None:
        size = load_scene(mi, req.scene).sensors()[0].film().crop_size()
        res = (int(size[0]), int(size[1]))
    t0 = time.perf_counter()
    v, f, rays, meta = cached_recording(mi, req.scene, res, req.spp, req.seed, req.cap)
    record_s = time.perf_counter() - t0
    if len(f) == 0:
        raise ValueError(f"{req.scene}: the scene has no triangles to trace")
    missing = [k for k in req.kinds if k not in rays]
    sets = [RaySet(k, *rays[k], any_hit=k in ANY_HIT_KINDS) for k in req.kinds if k in rays]
    if not sets:
        raise ValueError(f"the render traced none of the kinds asked for ({', '.join(req.kinds)}) at "
                         f"{res[0]}x{res[1]}, {req.spp} spp")
    settings = LocalitySettings(modes=req.modes, warps=req.warps, presets=req.presets,
                                treelet_heights=req.treelet_heights, sample=req.sample, seed=req.seed, check=req.check,
                                segments=req.segments, branching=req.branching, tail_steps=req.tail_steps)
    per_preset = sum(len(req.warps or (named_preset(p).warp,)) for p in req.presets) * len(req.segments or (None,))
    total = per_preset * len(req.modes) * len(req.treelet_heights) * len(sets)
    with tqdm(total=total, desc="locality", unit="replay", disable=not progress, file=sys.stderr) as bar:
        def step(done, _total, label):
            bar.set_postfix_str(label, refresh=False)
            bar.update(1)
        run = measure(v, f, sets, settings, req.leaf_size, progress=step)
    doc = run.as_dict()
    doc.update({
        "scene": str(req.scene), "resolution": list(res), "spp": req.spp, "seed": req.seed,
        "triangles": int(len(f)), "branching": req.branching, "tail_steps": req.tail_steps,
        "leaf_size": layerbvh.default_leaf_size(req.branching) if req.leaf_size is None else req.leaf_size,
        "record_s": record_s,
        "kinds": {k: {"recorded": int(len(rays[k][0])), "traced": meta["kinds"][k]["traced"]}
                  for k in req.kinds if k in rays},
        "kinds_missing": missing, "sampled": req.sample,
        "presets": {r.preset: r.preset_params for r in run.rows},
        "machine": machine(),
        "preset_lines": list(dict.fromkeys(Preset(**{**r.preset_params, "levels": tuple(CacheLevel(**lv) for lv in
                                                     r.preset_params["levels"])}).describe() for r in run.rows)),
    })
    # Every conclusion says what its model was checked against (issue 57 item 5).
    kinds = {name: params.get("kind", "gpu") for name, params in doc["presets"].items()}
    doc["model_checked"] = model_checked.notes(kinds)
    doc["preset_verdict"] = model_checked.with_note(doc["preset_verdict"], doc["model_checked"])
    return doc


def steps_text(k: int) -> str:
    """'1 step', 'k steps': a step cap as the sections write it."""
    return f"{k} step" + ("" if k == 1 else "s")


def machine() -> dict:
    """Where the model ran (its numbers do not depend on it, its run time and the cpu preset do)."""
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "llvm_vector_width": llvm_vector_width()}


def rows_of(doc: dict, scene: str | None = None) -> list:
    """A locality.json's rows (of one scene, in a sweep's merged document) as LocalityRows."""
    names = set(LocalityRow.__dataclass_fields__)
    return [LocalityRow(**{k: v for k, v in r.items() if k in names}) for r in doc["results"]
            if scene is None or r.get("scene") == scene]


def headline(doc: dict) -> dict:
    """The sweep table's figures of a one-kind document: per_ray against layer_sorted on the first
    preset at its first warp width and the first treelet height."""
    rows = doc["results"]
    first = rows[0]
    config = ("preset", "warp", "treelet_height", "branching")
    sel = {r["mode"]: r for r in rows if tuple(r.get(c) for c in config) == tuple(first.get(c) for c in config)}
    p, s = sel.get("per_ray"), sel.get("layer_sorted")
    return {"rays": first["kind"], "preset": first["preset"], "warp": first["warp"],
            "per_ray_transactions": p and p["transactions_per_ray"],
            "sorted_transactions": s and s["transactions_per_ray"],
            "per_ray_dram_bytes": p and p["dram_bytes_per_ray"], "sorted_dram_bytes": s and s["dram_bytes_per_ray"],
            "sorted_sort_bytes": s and s["sort_bytes_per_ray"],
            "sorted_total_vs_per_ray": (s["total_dram_bytes_per_ray"] / p["total_dram_bytes_per_ray"])
            if p and s and p["total_dram_bytes_per_ray"] else None,
            "trace_exact": all(c["exact"] for c in doc["checks"]) if doc["checks"] else None}


# -- outputs ------------------------------------------------------------------------------------------

MEANING = (
    "What the numbers mean: every read of the traversal kernels (node and triangle records, entry "
    "stacks, the ray and its state at the start of a kernel, the local stack) is replayed from an exact "
    "trace of the kernel's own loop, lane by lane in the order the kernels run: `per_ray` warps are W "
    "consecutive rays, wavefront steps' warps W consecutive rays of that step's sorted (or unsorted) "
    "order. A warp's load is one transaction per distinct segment its lanes touch (coalescing); each "
    "transaction goes through set-associative LRU caches (one L1 per SM or core, a shared L2, and the "
    "CPU's L3) with resident warps interleaved round-robin. DRAM bytes are what the last level misses; "
    "'between steps' is what a wavefront step moves besides its kernel's loads (every lane's sort key, "
    "the state record of each ray that goes on, the entries it still holds written above its global "
    "stack, the sort, the permutation; the next step's gather of each state record is one of its "
    "kernel's loads), counted as DRAM traffic; 'hits written' what every mode writes to its results "
    "(per_ray each ray's hit once, the layer modes each closer hit as found), in the total; per ray and "
    "step, the break-even is what a step may move and still cost the bus less than per_ray (the layer "
    "kernels' own excess subtracted; negative: the kernels alone read more), and the lower bound what "
    "any exact multi-exit design must move (the next state of each ray that goes on and the entries it "
    "holds). The model leaves out instruction costs, latency "
    "hiding, write traffic inside the kernels, prefetching and the real replacement policies; on CUDA, "
    "where rcp is approximate, a few rays may take another path than the LLVM kernel the trace is checked "
    "against.")


def height_table(rows: list) -> str:
    """layer_sorted against per_ray per kind and treelet height (one preset's rows, at its headline
    warp width and branching): the sorted path's total DRAM bytes over per_ray's, and its steps per
    ray. Empty when only one height was measured."""
    warp, _, k = headline_config(rows)
    mine = [r for r in rows if r.warp == warp and r.branching == k]
    heights = sorted({r.treelet_height for r in mine})
    if len(heights) < 2:
        return ""
    out = "| kind | " + " | ".join(f"H={h}: total ÷ per_ray, steps/ray" for h in heights) + " |\n|" + \
        "---|" * (len(heights) + 1) + "\n"
    for kind in dict.fromkeys(r.kind for r in mine):
        cells = []
        for h in heights:
            g = {r.mode: r for r in mine if r.kind == kind and r.treelet_height == h}
            p_, s_ = g.get("per_ray"), g.get("layer_sorted")
            cells.append(f"{s_.total_dram_bytes_per_ray / p_.total_dram_bytes_per_ray:.2f}×, {s_.steps_per_ray:.2f}"
                         if p_ and s_ and p_.total_dram_bytes_per_ray else "–")
        out += f"| {kind} | " + " | ".join(cells) + " |\n"
    return out


def table_compact(rows: list) -> str:
    """Per kind and mode: the figures BENCHMARKS.md shows."""
    cols = ("kind", "mode", "rays", "node tx/ray", "SIMD eff.", "L1 hit", "L2 hit", "node+tri DRAM B/ray",
            "kernel DRAM B/ray", "between steps B/ray", "hits written B/ray", "set-up B/ray", "total B/ray",
            "steps/ray",
            "between steps B/ray/step",
            "break-even B/ray/step", "lower bound B/ray/step")
    out = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"

    def num(x):
        return "–" if x is None else f"{x:.0f}"
    for r in rows:
        out += (f"| {r.kind} | {r.mode} | {r.rays:,} | {r.node_transactions_per_ray:.1f} | {r.simd_efficiency:.2f} | "
                f"{r.l1_hit_rate:.2f} | {r.l2_hit_rate:.2f} | "
                f"{r.node_dram_bytes_per_ray + r.triangle_dram_bytes_per_ray:.0f} | {r.dram_bytes_per_ray:.0f} | "
                f"{r.sort_bytes_per_ray:.0f} | {r.result_bytes_per_ray:.0f} | {num(r.setup_bytes_per_ray)} | "
                f"{r.total_dram_bytes_per_ray:.0f} | "
                f"{r.steps_per_ray:.1f} | "
                f"{num(r.sort_bytes_per_ray_step if r.mode != 'per_ray' else None)} | "
                f"{num(r.break_even_bytes_per_ray_step)} | {num(r.lower_bound_bytes_per_ray_step)} |\n")
    return out


def benchmarks_section(doc: dict, fig_rel: str) -> str:
    """BENCHMARKS.md's locality section from a locality.json (one scene, or a sweep's merged
    document): the command, the machine, the presets, then per scene its verdict per preset, a
    table per preset and the plot (fig_rel/locality_SCENE.png, written by write_figures)."""
    m = doc.get("machine") or {}
    parts = ["## Locality: memory transactions and cache hits (`layerbvh locality`)", "", MEANING, "",
             f"Command: `{doc['command']}`" + (f" ({m.get('cpu')}, {m.get('cores')} cores, Dr.Jit LLVM "
                                                f"{m.get('llvm_vector_width')} lanes)" if m else ""), "",
             "Presets:", ""] + [f"- {line}" for line in doc["preset_lines"]] + [""]
    for scene in _scenes(doc):
        rows = rows_of(doc, scene if "scenes" in doc else None)
        info = doc["scenes"][scene] if "scenes" in doc else doc
        kinds = ", ".join(f"{k} {v['recorded']:,}" for k, v in info["kinds"].items())
        exact = all(c["exact"] for c in doc["checks"] if c.get("scene", scene) == scene)
        parts += [f"### {scene} ({info['triangles']:,} triangles)", "",
                  f"Rays recorded at {info['resolution'][0]}x{info['resolution'][1]}, {info['spp']} spp: {kinds}"
                  + (f", each sampled to at most {info['sampled']:,}" if info.get("sampled") else "")
                  + "; the layer modes' tail after "
                  + f"{steps_text(info.get('tail_steps', LocalityRow.tail_steps))} at most. "
                  + "Trace "
                  + ("checked against the kernel: every ray's hit, work counts and loads of each kind equal."
                     if exact else "check FAILED on some rays: see the run's summary.md."), ""]
        checked = model_checked.notes({r.preset: r.preset_params.get("kind", "gpu") for r in rows})
        parts += [f"- {v}" for v in model_checked.with_note(preset_verdict(rows), checked).values()] + [""]
        first = [r for r in rows if r.preset == rows[0].preset]
        by_height = height_table(first)
        if by_height:
            warp, _, k = headline_config(first)
            parts += [f"Against the treelet height ({rows[0].preset}, W={warp}, K={k}; layer_sorted's total DRAM "
                      f"bytes, between steps included, over per_ray's, and its steps per ray):", "", by_height]
        for pre in dict.fromkeys(r.preset for r in rows):
            mine = [r for r in rows if r.preset == pre]
            warp, h, k = headline_config(mine)
            parts += [f"{pre}, W={warp}, H={h}, K={k}:", "", table_compact(at_headline(mine))]
        parts += [f"![DRAM bytes per ray]({fig_rel}/locality_{_slug(scene)}.png)", ""]
    return "\n".join(parts)


def merge_documents(docs: list) -> dict:
    """Several locality.json documents (single runs, or sweeps' merged ones) as one merged document,
    a row kept once per (scene, kind, mode, warp, preset, treelet height, branching): the first document's wins."""
    merged = {"command": " ; ".join(d["command"] for d in docs), "results": [], "checks": [], "verdict": [],
              "presets": {}, "preset_lines": [], "scenes": {}, "machine": docs[0].get("machine")}
    seen = set()
    for d in docs:
        if "scenes" not in d:  # one `layerbvh locality` run: its scene by name
            name = _slug(d["scene"])
            d = {**d, "results": [{**r, "scene": name} for r in d["results"]],
                 "checks": [{**c, "scene": name} for c in d["checks"]],
                 "scenes": {name: {k: d[k] for k in ("resolution", "spp", "triangles", "kinds", "sampled", "tail_steps")
                                   if k in d}}}
        for r in d["results"]:
            key = tuple(r.get(k, 2) if k == "branching" else r[k]
                        for k in ("scene", "kind", "mode", "warp", "preset", "treelet_height", "branching"))
            if key not in seen:
                seen.add(key)
                merged["results"].append(r)
        merged["checks"] += d["checks"]
        merged["verdict"] += d.get("verdict", [])
        merged["presets"].update(d["presets"])
        merged["preset_lines"] = list(dict.fromkeys(merged["preset_lines"] + d["preset_lines"]))
        for name, info in d["scenes"].items():
            merged["scenes"].setdefault(name, info)
    return merged


def _scenes(doc: dict) -> list:
    return list(doc["scenes"]) if "scenes" in doc else [Path(doc["scene"]).name]


def _slug(scene: str) -> str:
    return Path(scene).stem if Path(scene).stem != "scene" else Path(scene).parent.name or "scene"


def write_figures(doc: dict, folder) -> None:
    """locality_SCENE.png of every scene of the document."""
    for scene in _scenes(doc):
        sub = {**doc, "scene": scene, "results": [r for r in doc["results"] if r.get("scene", scene) == scene]}
        atomic.write_bytes(Path(folder) / f"locality_{_slug(scene)}.png", plot_png(sub))


def plot_png(doc: dict) -> bytes:
    """DRAM bytes per ray as stacked bars, one panel per (preset, kind): a group of bars per treelet
    height, a bar per mode and warp width; stacks: node records, triangle records, the rest of the
    traversal kernels' reads (rays, state, entry stacks), and the layer modes' traffic between
    steps (hatched)."""

    import matplotlib  # local: matplotlib loads only when a plot is drawn
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # local: matplotlib loads only when a plot is drawn
    rows = doc["results"]
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    fig, axes = plt.subplots(len(presets), len(kinds), figsize=(3.8 * len(kinds), 3.0 * len(presets)), squeeze=False)
    parts = (("node records", "node_dram_bytes_per_ray", "tab:blue", None),
             ("triangle records", "triangle_dram_bytes_per_ray", "tab:orange", None),
             ("rays, state, stacks", None, "tab:gray", None),
             ("between steps", "sort_bytes_per_ray", "white", "///"),
             ("hits written", "result_bytes_per_ray", "tab:green", None))
    for i, p in enumerate(presets):
        for j, k in enumerate(kinds):
            ax = axes[i][j]
            sel = [r for r in rows if r["preset"] == p and r["kind"] == k]
            # (one tree per plot: the headline branching's rows, a render's tree if it was measured)
            ks = {r.get("branching", 2) for r in sel}
            tree = layerbvh.DEFAULT_BRANCHING if layerbvh.DEFAULT_BRANCHING in ks else min(ks)
            sel = [r for r in sel if r.get("branching", 2) == tree]
            bars = sorted({(r["mode"], r["warp"]) for r in sel}, key=lambda mw: (mw[1], layerbvh.MODES.index(mw[0])))
            heights = sorted({r["treelet_height"] for r in sel})
            width = 0.8 / max(len(bars), 1)
            ticks, labels = [], []
            for g, h in enumerate(heights):
                here = [(mode, w) for mode, w in bars
                        if any(r["treelet_height"] == h and r["mode"] == mode and r["warp"] == w for r in sel)]
                for b, (mode, w) in enumerate(here):  # a group's bars centred on it, however many it has
                    r = next(r for r in sel if r["treelet_height"] == h and r["mode"] == mode and r["warp"] == w)
                    x = g + (b - (len(here) - 1) / 2) * width
                    node, tri = r["node_dram_bytes_per_ray"], r["triangle_dram_bytes_per_ray"]
                    values = (node, tri, r["dram_bytes_per_ray"] - node - tri, r["sort_bytes_per_ray"],
                              r.get("result_bytes_per_ray", 0.0))
                    bottom = 0.0
                    for (label, _, colour, hatch), val in zip(parts, values):
                        ax.bar(x, val, width * 0.9, bottom=bottom, color=colour, hatch=hatch, edgecolor="k",
                               linewidth=0.4, label=label if (g, b) == (0, 0) else None)
                        bottom += val
                    ticks.append(x)
                    short = {"per_ray": "per", "layer_sorted": "sort", "layer_unsorted": "uns"}.get(mode, mode)
                    labels.append(f"{short}\n{w}")
                if len(heights) > 1:
                    ax.text(g, -0.22, f"H={h}", transform=ax.get_xaxis_transform(), ha="center", fontsize=7)
            ax.set_xticks(ticks, labels, fontsize=6)
            ax.set_title(f"{k} - {p}" + (f" (H={heights[0]})" if len(heights) == 1 else ""), fontsize=9)
            ax.set_ylabel("DRAM bytes / ray", fontsize=8)
            ax.set_xlabel("mode, warp width" + (" / treelet height" if len(heights) > 1 else ""), fontsize=7,
                          labelpad=12 if len(heights) > 1 else 2)
            ax.tick_params(axis="y", labelsize=7)
            if i == 0 and j == 0:
                ax.legend(fontsize=6)
    fig.suptitle(f"{Path(doc['scene']).name}: DRAM bytes per ray by mode (model; see summary.md for the presets)",
                 fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


TABLE_COLUMNS = ("kind", "preset", "warp", "treelet_height", "mode", "rays", "inner_per_ray", "tris_per_ray",
                 "transactions_per_ray", "node_transactions_per_ray", "simd_efficiency", "l1_hit_rate", "l2_hit_rate",
                 "dram_bytes_per_ray", "sort_bytes_per_ray", "total_dram_bytes_per_ray")


def table_md(rows: list) -> str:
    """The rows as a Markdown table (TABLE_COLUMNS)."""
    def cell(v):
        return f"{v:.3g}" if isinstance(v, float) else str(v)
    head = "| " + " | ".join(TABLE_COLUMNS) + " |\n|" + "---|" * len(TABLE_COLUMNS) + "\n"
    return head + "".join("| " + " | ".join(cell(r[c]) for c in TABLE_COLUMNS) + " |\n" for r in rows)


def summary_md(doc: dict, command: str) -> str:
    bad = [c for c in doc["checks"] if not c["exact"]]
    check = ("every mode's trace matched the kernel on every ray (hits, work counts, loads per kind)" if not bad else
             f"{len(bad)} trace check(s) found rays where the replay and the kernel differ: " +
             "; ".join(f"{c['kind']} {c['mode']}: {c['hit_mismatches']} hits, {c['work_mismatches']}, loads "
             f"{c.get('load_mismatches')}" for c in bad))
    lines = [f"# Locality: {doc['scene']}", "", f"Command: `{command}`", "",
             f"{doc['triangles']:,} triangles in a {doc.get('branching', 2)}-wide BVH (leaves of at most "
             f"{doc['leaf_size']}); rays recorded at {doc['resolution'][0]}x{doc['resolution'][1]}, "
             f"{doc['spp']} spp: " + ", ".join(f"{k} {v['recorded']:,}" for k, v in doc["kinds"].items())
             + (f" (each sampled to at most {doc['sampled']:,})" if doc["sampled"] else "") + ".",
             f"Trace check: {check}.", "", "Presets:", ""]
    lines += [f"- {p}" for p in doc["preset_lines"]]
    lines += ["", "## Verdict", ""] + [f"- {v}" for v in doc["preset_verdict"].values()]
    lines += ["", "Per kind of rays:", ""] + [f"- {v}" for v in doc["verdict"]]
    lines += ["", "## Rows", "", table_md(doc["results"])]
    return "\n".join(lines)


def write_outputs(out, doc: dict, command: str) -> None:
    """DIR/locality.json, locality.png, summary.md, written whole or not at all."""
    doc = {**doc, "command": command}
    with atomic.atomic_folder(out, OUTPUT_MARKER) as tmp:
        atomic.write_bytes(tmp / "locality.png", plot_png(doc))
        atomic.write_text(tmp / "summary.md", summary_md(doc, command))
        atomic.write_text(tmp / OUTPUT_MARKER, json.dumps(json_safe(doc), indent=1, allow_nan=False))


def run(mi, args, command: str) -> int:
    """The `layerbvh locality` command (options checked by the CLI)."""
    req = request_from_args(args)
    doc = measure_scene(mi, req, progress=not args.no_progress)
    write_outputs(args.out, doc, command)
    for line in doc["preset_verdict"].values():
        print(line)
    bad = [c for c in doc["checks"] if not c["exact"]]
    if bad:
        print(f"warning: {len(bad)} trace check(s) differ from the kernel (see summary.md)", file=sys.stderr)
    print(str(Path(args.out).resolve() / OUTPUT_MARKER))
    return 0


def add_parser(sub) -> None:
    """The `locality` subcommand's options."""
    lp = sub.add_parser("locality", help="memory transactions and cache hits of the scene's rays in SIMT warps / "
                                         "SIMD packets, per traversal mode (a memory model over an exact trace)")
    lp.add_argument("scene", help="Mitsuba 3 XML scene")
    lp.add_argument("--out", required=True, help="output folder (locality.json, locality.png, summary.md)")
    lp.add_argument("--res", type=int, nargs=2, metavar=("W", "H"), help="film resolution (default: the scene's)")
    lp.add_argument("--spp", type=int, help=f"samples per pixel of the recording render (default {DEFAULT_SPP})")
    lp.add_argument("--seed", type=int, default=0)
    lp.add_argument("--rays", default=",".join(DEFAULT_KINDS),
                    help=f"comma list of ray kinds: {', '.join(KINDS)} (default %(default)s)")
    lp.add_argument("--warp", help="comma list of warp/packet widths, e.g. 8,16,32 (default: each preset's own: "
                                   "32 on the GPUs, the CPU's SIMD lanes)")
    lp.add_argument("--preset", default=",".join(DEFAULT_PRESETS),
                    help=f"comma list of hardware presets: {', '.join(PRESETS)} (default %(default)s)")
    lp.add_argument("--segment", help="comma list of transaction sizes in bytes, e.g. 32,128 (default: each preset's "
                                      "own: 32-byte sectors on the GPUs, 64-byte lines on the CPU); a size above a "
                                      "level's line makes that level allocate lines of that size")
    lp.add_argument("--treelet-heights", default=str(layerbvh.DEFAULT_TREELET_HEIGHT),
                    help="comma list of treelet heights (default %(default)s)")
    lp.add_argument("--modes", default=",".join(layerbvh.MODES), help="comma list of modes (default %(default)s)")
    lp.add_argument("--branching", type=int, default=layerbvh.DEFAULT_BRANCHING, choices=layerbvh.BRANCHINGS,
                    help="children per BVH node of the tree replayed (default %(default)s, a render's)")
    lp.add_argument("--leaf-size", type=int, help="triangles per BVH leaf at most (default: 4 binary, 2 wide)")
    lp.add_argument("--sample", type=int, help="replay at most N rays per kind, drawn uniformly (default: all)")
    lp.add_argument("--cap", type=int, default=DEFAULT_CAP, help="rays recorded per kind at most (default %(default)s)")
    lp.add_argument("--tail-steps", type=int, help="wavefront steps after which the layer modes finish the rays "
                    f"left per ray, in the order the last step sorted them (default {TAIL_STEPS})")
    lp.add_argument("--no-check", action="store_true", help="skip comparing each mode's trace with the kernel")
    lp.add_argument("--variant", default="llvm_ad_rgb",
                    help="Mitsuba variant: any llvm_* or cuda_* (default %(default)s)")
    lp.add_argument("--no-progress", action="store_true")
