"""A traversal benchmark's timed configurations and the figures made of them: agreement between modes, the result
rows with their ratios, the printed table."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

import layerbvh

MIB = 1 << 20


@dataclass
class Config:
    """One timed configuration: `run(stats)` traces every ray once and returns (seconds, prim, stats).

    The warm-up run counts work (stats=True); the timed runs do not, as a renderer would not:
    `stats` keeps the warm-up's work counts, `time_stats` a timed run's steps and time split."""

    mode: str
    height: int | None
    run: Callable
    branching: int | None = None  # children per node of the layerbvh layout (None: Embree)
    build_s: float | None = None
    bvh_bytes: int | None = None
    times: list = field(default_factory=list)
    prim: np.ndarray | None = None
    stats: object = None
    time_stats: object = None
    rss_peak: int | None = None
    rss_extra: int | None = None

    @property
    def label(self) -> str:
        return self.mode if self.height is None else layout_label(self.mode, self.branching, self.height)


def layout_label(mode: str, branching: int, height: int) -> str:
    """How a configuration is named in tables: its mode, its layout's branching and treelet height."""
    return f"{mode} K={branching} h={height}"

# -- figures ----------------------------------------------------------------------------------------


def prim_mismatches(configs: list[Config]) -> dict:
    """Per config label: how many rays' prim differs from per_ray's."""
    ref = next(c for c in configs if c.mode == "per_ray")
    return {c.label: int((c.prim != ref.prim).sum()) for c in configs}


def print_agreement(diff: dict, n: int, any_hit: bool = False) -> None:
    what = "occlusion answer" if any_hit else "prim"
    for label, k in diff.items():
        if k and label != "embree":  # layer modes walk the same tree in the same order: must agree exactly
            print(f"WARNING: {label} returns a different {what} than per_ray on {k:,} of {n:,} rays")
    if diff["embree"] and any_hit:
        print(f"note: Embree's occlusion answer differs from per_ray on {diff['embree']:,} of {n:,} rays "
              f"({1e6 * diff['embree'] / n:.1f} ppm; shared edges and hits at tmax)")
    elif diff["embree"]:
        # Embree may pick the other triangle of a shared edge, so this is a note, not a failure.
        print(f"note: Embree's prim differs from per_ray on {diff['embree']:,} of {n:,} rays "
              f"({1e6 * diff['embree'] / n:.1f} ppm)")
    if not any(k for label, k in diff.items() if label != "embree"):
        print(f"all layerbvh modes and heights return the same {what} for every ray")


def result_rows(mesh: str, tris: int, kind: str, configs: list[Config], n: int, diff: dict,
                any_hit: bool = False, source: str = "generated") -> list[dict]:
    mrays = {c.label: [n / t / 1e6 for t in c.times] for c in configs}
    med = {k: float(np.median(v)) for k, v in mrays.items()}
    # The baseline is the fastest per_ray over the layouts benched (the strongest one).
    per_ray = max(med[c.label] for c in configs if c.mode == "per_ray")
    rows = []
    for c in configs:
        s = c.stats
        # auto against the faster (by median) of the two modes it chooses between, same layout:
        # the median of per-round ratios, since auto runs next to both in every round and a
        # round's neighbours share the machine's state of the moment
        best_of = None
        if c.mode == "auto":
            faster = max((layout_label("per_ray", c.branching, c.height),
                          layout_label("layer_sorted", c.branching, c.height)), key=lambda k: med[k])
            best_of = float(np.median([a / b for a, b in zip(mrays[c.label], mrays[faster])]))
        rows.append({
            "mesh": mesh, "triangles": tris, "rays": kind, "mode": c.mode, "treelet_height": c.height,
            "branching": c.branching,
            "mrays_s": med[c.label], "runs": mrays[c.label], "build_s": c.build_s,
            "bvh_bytes": c.bvh_bytes, "work_bytes": s.work_bytes if s else None,
            "ratio_per_ray": med[c.label] / per_ray, "ratio_embree": med[c.label] / med["embree"],
            "ratio_per_ray_same_h": (med[c.label] / med[layout_label("per_ray", c.branching, c.height)]
                                     if c.height else None),
            "inner_per_ray": s.inner_nodes_per_ray if s else None,
            "leaves_per_ray": s.leaves_per_ray if s else None,
            "tris_per_ray": s.triangles_per_ray if s else None,
            "iterations_per_ray": s.per_ray("iterations") if s else None,
            # each inner-node visit slab-tests all of the node's child slots: box tests go up with
            # the branching while iterations and dependent node loads (= inner visits) go down
            "box_tests_per_ray": s.inner_nodes_per_ray * c.branching if s else None,
            "steps": s.steps if s else None,
            "ray_count": n, "query": "any_hit" if any_hit else "closest_hit", "source": source,
            "hit_fraction": float(np.mean(c.prim != (0 if any_hit else layerbvh.MISS))),
            "prim_mismatch_vs_per_ray": diff[c.label],
            "rss_peak_bytes": c.rss_peak, "rss_extra_bytes": c.rss_extra,
            "auto_choice": s.mode if c.mode == "auto" and s else None,
            "ratio_best_of_two": best_of,
            "time_split_s": time_split(s, c.time_stats),
        })
    return rows


def time_split(work, timed) -> dict | None:
    """Seconds per stage of a timed run; its kernel time is split into treelet and leaf work by
    the warm-up's share of loop iterations spent on triangles (the timed run counts no work)."""
    if work is None:
        return None
    t = timed or work
    share = work.triangles / work.iterations if work.iterations else 0.0
    return {"sort": t.time_sort_s, "treelet": t.time_traverse_s * (1 - share), "leaf": t.time_traverse_s * share,
            "other": t.time_other_s, "total": t.time_total_s}


def mode_label(r: dict) -> str:
    """The mode, and for auto what it chose (e.g. `auto (per_ray)`)."""
    if r["mode"] == "auto" and r.get("auto_choice"):
        return f"auto ({r['auto_choice'].split(':', 1)[-1]})"
    return r["mode"]


def _fmt(x, spec):
    return "–" if x is None else format(x, spec)


def print_table(rows: list[dict]) -> None:
    r0 = next(r for r in rows if r["mode"] == "per_ray")
    query = "any-hit" if r0["query"] == "any_hit" else "closest-hit"
    print(f"\n## {r0['mesh']} ({r0['triangles']:,} triangles), {r0['rays']} rays, {query} "
          f"({r0['ray_count']:,}, {100 * r0['hit_fraction']:.1f}% hit per per_ray)\n")
    print("| mode | K | h | Mrays/s | runs min–max | × per_ray | × Embree | inner/ray | box tests/ray | iters/ray "
          "| leaves/ray | tris/ray | steps | build s | build Mtris/s | BVH MiB | work MiB | peak RSS +MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        build_rate = r["triangles"] / r["build_s"] / 1e6 if r["build_s"] else None
        print(f"| {mode_label(r)} | {_fmt(r['branching'], 'd')} | {_fmt(r['treelet_height'], 'd')} "
              f"| {r['mrays_s']:.2f} "
              f"| {min(r['runs']):.2f}–{max(r['runs']):.2f} | {r['ratio_per_ray']:.2f} | {r['ratio_embree']:.2f} "
              f"| {_fmt(r['inner_per_ray'], '.1f')} | {_fmt(r['box_tests_per_ray'], '.1f')} "
              f"| {_fmt(r['iterations_per_ray'], '.1f')} | {_fmt(r['leaves_per_ray'], '.2f')} "
              f"| {_fmt(r['tris_per_ray'], '.1f')} | {_fmt(r['steps'], 'd')} | {_fmt(r['build_s'], '.2f')} "
              f"| {_fmt(build_rate, '.2f')} | {_fmt(r['bvh_bytes'] and r['bvh_bytes'] / MIB, '.1f')} "
              f"| {_fmt(r['work_bytes'] and r['work_bytes'] / MIB, '.1f')} "
              f"| {_fmt(r['rss_extra_bytes'] and r['rss_extra_bytes'] / MIB, '.0f')} |")
