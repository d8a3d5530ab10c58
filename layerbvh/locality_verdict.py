"""The locality tool's verdicts: one sentence per kind of rays and configuration, and one per preset, on what sorting
does to DRAM traffic."""
from __future__ import annotations

from .inputs import DEFAULT_BRANCHING, DEFAULT_TREELET_HEIGHT


def _ratio(a: float, b: float) -> float:
    return a / b if b else float("nan")


def verdict(rows: list) -> list[str]:
    """One sentence per (kind, preset, warp, treelet height): what sorting does to the traversal's
    node and triangle traffic (the paper's claim), to all of its kernels' DRAM traffic, and to the
    memory bus once the steps' own traffic is paid."""
    out = []
    for (kind, pre, warp, h, k), g in _groups(rows, lambda r: (r.kind, r.preset, r.warp, r.treelet_height,
                                                                r.branching)).items():
        if "per_ray" not in g or "layer_sorted" not in g:
            continue
        p, s = g["per_ray"], g["layer_sorted"]
        nt = _ratio(s.node_dram_bytes_per_ray + s.triangle_dram_bytes_per_ray,
                    p.node_dram_bytes_per_ray + p.triangle_dram_bytes_per_ray)
        tx = _ratio(s.node_transactions_per_ray, p.node_transactions_per_ray)
        reads = _ratio(s.dram_bytes_per_ray, p.dram_bytes_per_ray)
        total = _ratio(s.total_dram_bytes_per_ray, p.total_dram_bytes_per_ray)
        out.append(
            f"{kind}, {pre}, W={warp}, H={h}, K={k}: sorted steps issue {tx:.2f}x "
            f"per_ray's node transactions (SIMD efficiency {s.simd_efficiency:.2f} vs {p.simd_efficiency:.2f}) "
            f"and read {nt:.2f}x its node and triangle bytes from DRAM; all kernel reads {reads:.2f}x, "
            f"with the {s.sort_bytes_per_ray:.0f} B/ray moved between steps"
            + (" and the hits written" if s.setup_bytes_per_ray is None or p.setup_bytes_per_ray is None else
               f", the hits written and the set-up's passes ({s.setup_bytes_per_ray:.0f} B/ray against "
               f"per_ray's {p.setup_bytes_per_ray:.0f})")
            + f" {total:.2f}x: sorting "
            + ("wins on memory traffic" if s.total_dram_bytes_per_ray < p.total_dram_bytes_per_ray
               else "does not pay for itself in memory traffic")
            + (f" (per ray and step it moves {s.sort_bytes_per_ray_step:.0f} B; break-even "
               f"{s.break_even_bytes_per_ray_step:.0f} B, lower bound {s.lower_bound_bytes_per_ray_step:.0f} B)."
               if s.break_even_bytes_per_ray_step is not None else "."))
    return out


def headline_config(rows: list) -> tuple:
    """(warp, treelet height, branching) a preset's one-sentence verdict and tables use: its first
    warp width in `rows`, and the default treelet height and branching if they were measured, else
    the first."""
    heights, ks = [r.treelet_height for r in rows], [r.branching for r in rows]
    return (rows[0].warp, DEFAULT_TREELET_HEIGHT if DEFAULT_TREELET_HEIGHT in heights else heights[0],
            DEFAULT_BRANCHING if DEFAULT_BRANCHING in ks else ks[0])


def at_headline(rows: list) -> list:
    """The rows (locality.LocalityRow) of headline_config (one preset's rows)."""
    warp, h, k = headline_config(rows)
    return [r for r in rows if (r.warp, r.treelet_height, r.branching) == (warp, h, k)]


def preset_verdict(rows: list) -> dict:
    """One sentence per preset over every kind of rays (at headline_config): the verdict
    BENCHMARKS.md states per scene and preset."""
    out = {}
    for pre in dict.fromkeys(r.preset for r in rows):
        mine = [r for r in rows if r.preset == pre]
        warp, h, k = headline_config(mine)
        kinds = _groups(at_headline(mine), lambda r: r.kind)
        nt, tot = {}, {}
        for kind, g in kinds.items():
            if "per_ray" in g and "layer_sorted" in g:
                p, s = g["per_ray"], g["layer_sorted"]
                nt[kind] = _ratio(s.node_dram_bytes_per_ray + s.triangle_dram_bytes_per_ray,
                                  p.node_dram_bytes_per_ray + p.triangle_dram_bytes_per_ray)
                tot[kind] = _ratio(s.total_dram_bytes_per_ray, p.total_dram_bytes_per_ray)
        if not nt:
            continue
        gain = [k for k, v in nt.items() if v < 0.9]
        wins = [k for k, v in tot.items() if v < 1.0]
        def span(d):
            lo, hi = min(d.values()), max(d.values())
            return f"{lo:.2f}x" if f"{lo:.2f}" == f"{hi:.2f}" else f"{lo:.2f}-{hi:.2f}x"
        out[pre] = (
            f"{pre} (W={warp}, H={h}, K={k}): sorting "
            + (f"cuts the node and triangle bytes read from DRAM on {', '.join(f'{k} ({nt[k]:.2f}x)' for k in gain)}"
               if gain else f"does not cut the node and triangle bytes read from DRAM ({span(nt)} of per_ray's)")
            + "; counting the ray state, entry stacks, the traffic between steps and the hits written"
            + (", and the set-up's passes, " if all(r.setup_bytes_per_ray is not None for r in mine) else ", ")
            + f"the sorted path moves {span(tot)} per_ray's DRAM bytes, so "
            + (f"it wins on memory traffic for {', '.join(wins)}." if wins else
               "it does not pay for itself in memory traffic on any kind of rays."))
    return out


def _groups(rows, key) -> dict:
    """rows grouped by key(row), each group {mode: row}."""
    groups: dict = {}
    for r in rows:
        groups.setdefault(key(r), {})[r.mode] = r
    return groups
