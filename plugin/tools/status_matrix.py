"""The README's status matrix (issue 58): per mirrored integrator, what the suite compares with stock (variants,
derivative keys, polarized modes) and its known divergences, each cell naming the pytest nodes behind it."""
from __future__ import annotations

import argparse
import inspect
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT

SECTION = "status_matrix"
NOT_TESTED = "not compared"

R = "tests/runtime/"


@dataclass
class Cell:
    """What one cell claims, and the pytest node ids (relative to the repository) that assert it."""

    text: str
    nodes: tuple = ()


@dataclass
class Row:
    integrator: str
    rgb: Cell
    spectral_mono: Cell = field(default_factory=lambda: Cell(NOT_TESTED))
    derivatives: Cell = field(default_factory=lambda: Cell("–"))
    polarized: Cell = field(default_factory=lambda: Cell(NOT_TESTED))
    divergences: Cell = field(default_factory=lambda: Cell("none known"))


COLUMNS = (("rgb", "against stock, RGB"), ("spectral_mono", "spectral, mono"), ("derivatives", "derivatives"),
           ("polarized", "polarized"), ("divergences", "known divergences from stock"))

# Each test file's node-id prefix.
BACKEND, POL, DIRECT = R + "test_mitsuba_backend.py::", R + "test_polarized.py::", R + "test_direct.py::"
VOL, MEDIA, PTR = R + "test_volpath.py::", R + "test_media_reference.py::", R + "test_ptracer.py::"
PRB, WRAP = R + "test_prb.py::", R + "test_wrappers.py::"
STOKES_SAME_SEED = POL + "test_stokes_around_ours_equals_stock_in_all_four_stokes_components[stokes-per_ray]"

ROWS = (
    Row("path",
        Cell("same seed, every traversal", (BACKEND + "test_same_seed_matches_stock[cbox-per_ray]",
                                           BACKEND + "test_same_seed_matches_stock[bunny_box-layer_sorted]")),
        Cell("registered only", (BACKEND + "test_registered_for_every_variant_set_later[variant]",)),
        polarized=Cell("inside stokes", (STOKES_SAME_SEED,)),
        divergences=Cell("instanced scenes drift after a few bounces (decided by the Z-test); "
                         "full-depth paths diverge (the verdict's second step)",
                         (R + "test_instancing.py::test_instanced_bunnies_pass_the_z_test_at_full_depth",
                          "tests/tools/test_verdict.py::"
                          "test_diverged_paths_of_a_full_depth_scene_agree_and_the_report_says_why"))),
    Row("direct",
        Cell("same seed", (DIRECT + "test_direct_matches_stock_direct_at_the_same_seed[cbox-default-per_ray]",)),
        Cell("same seed", (DIRECT + "test_direct_matches_stock_in_the_spectral_and_mono_variants",)),
        divergences=Cell("none; BSDF draw order probed from the wheel",
                         (DIRECT + "test_the_bsdf_draw_order_is_probed_from_the_wheel",))),
    Row("volpath",
        Cell("same seed, homogeneous media",
             (VOL + "test_mitsuba_media_scene_matches_stock_at_the_same_seed[test_homo_area_light]",)),
        Cell("same seed", (VOL + "test_volpath_matches_stock_in_the_spectral_and_mono_variants",)),
        polarized=Cell("same seed", (POL + "test_our_estimators_equal_stock_in_the_polarized_variants[volpath-auto]",)),
        divergences=Cell("heterogeneous media: paths diverge (chaotic null-collision chain); "
                         "Mitsuba's reference test and the verdict decide",
                         (VOL + "test_heterogeneous_media_agree_with_stock_within_noise",
                          MEDIA + "test_ours_passes_mitsubas_reference_test[test_hetero_sigmat]"))),
    Row("volpathmis",
        Cell("same seed",
             (VOL + "test_mitsuba_volpathmis_scenes_match_stock_at_the_same_seed[test_homo_spectral_sigmat]",
              VOL + "test_layer_sorted_matches_stock_with_volpathmis")),
        Cell("same seed", (VOL + "test_volpath_matches_stock_in_the_spectral_and_mono_variants",)),
        divergences=Cell("none known; Mitsuba's reference test on the heterogeneous scene",
                         (MEDIA + "test_volpathmis_passes_mitsubas_reference_test[test_hetero_spectral_sigmat]",))),
    Row("ptracer",
        Cell("the verdict (same seed, then statistics)",
             (PTR + "test_ptracer_agrees_with_stock[cbox-per_ray]",
              PTR + "test_ptracer_statistical_step_catches_a_2_percent_albedo_change"))),
    Row("prb",
        Cell("same seed (primal)", (PRB + "test_primal_same_seed_as_stock[prb-cbox-layer_sorted]",)),
        derivatives=Cell("forward and backward, same seed: reflectance, radiance, vertex positions, GGX alpha, "
                         "a textured area emitter's texels; paired test over render pairs",
                         (PRB + "test_gradients_same_seed_as_stock[prb-cbox-layer_sorted]",
                          PRB + "test_gradients_same_seed_as_stock[prb-bunny_box-per_ray]",
                          PRB + "test_gradients_same_seed_as_stock[prb-paper_mix-per_ray]",
                          PRB + "test_a_textured_area_emitter_differentiates_as_stock_in_the_wavefront_loop",
                          PRB + "test_gradient_statistical_step_and_its_negative_control"
                                "[LeftWallBSDF.brdf_0.reflectance.value-light]")),
        polarized=Cell("same seed",
                       (POL + "test_our_estimators_equal_stock_in_the_polarized_variants[prb-layer_sorted]",))),
    Row("prb_basic",
        Cell("same seed (primal)", (PRB + "test_primal_same_seed_as_stock[prb_basic-cbox-per_ray]",)),
        derivatives=Cell("forward and backward, same seed: reflectance, radiance, vertex positions",
                         (PRB + "test_gradients_same_seed_as_stock[prb_basic-cbox-per_ray]",
                          PRB + "test_gradients_same_seed_as_stock[prb_basic-bunny_box-layer_sorted]"))),
    Row("prbvolpath",
        Cell("same seed (primal)", (PRB + "test_primal_same_seed_as_stock[prbvolpath-cbox-layer_sorted]",)),
        derivatives=Cell("backward, same seed: a medium's albedo and extinction (forward refused, as stock refuses it)",
                         (PRB + "test_prbvolpath_in_media_same_seed_and_backward",))),
    Row("depth",
        Cell("same seed", (R + "test_depth.py::test_depth_matches_stock_depth_at_the_same_seed[cbox-per_ray]",))),
    Row("stokes",
        Cell("needs a polarized variant (refused by name)",
             (POL + "test_a_stokes_scene_outside_a_polarized_variant_names_the_variants_to_use",)),
        polarized=Cell("same seed, all four Stokes components; compare judges the five panels",
                       (STOKES_SAME_SEED, POL + "test_compare_judges_the_five_stokes_panels"))),
    Row("aov, moment",
        Cell("same seed, the wrapper on both sides",
             (WRAP + "test_a_wrapped_path_scene_compares_with_its_wrapper_on_both_sides[moment]",
              WRAP + "test_a_wrapped_path_scene_compares_with_its_wrapper_on_both_sides[aov]"))),
)


def nodes(rows=ROWS) -> list[str]:
    """Every node id the matrix names, once, in order."""
    seen = dict.fromkeys(n for row in rows for key, _ in COLUMNS for n in getattr(row, key).nodes)
    return list(seen)


def _cell(c: Cell) -> str:
    return c.text + "".join(f"<br>`{n.removeprefix(R).removeprefix('tests/')}`" for n in c.nodes)


def markdown(rows=ROWS) -> str:
    """The matrix as a markdown table (what the README holds between its status_matrix markers)."""
    lines = ["| integrator | " + " | ".join(title for _, title in COLUMNS) + " |",
             "|---" * (len(COLUMNS) + 1) + "|"]
    for row in rows:
        lines.append(f"| `{row.integrator}` | " + " | ".join(_cell(getattr(row, key)) for key, _ in COLUMNS) + " |")
    return "\n".join(lines)


def _rst_to_md(text: str) -> str:
    """A docstring's reStructuredText literals (``x``) as markdown's (`x`), its lines unindented."""
    return inspect.cleandoc(text).replace("``", "`")


def integrator_pages(rows=ROWS) -> dict[str, str]:
    """One documentation page per row, {"integrators/<name>.md": markdown}: the estimator that
    stands in for stock's (its docstring: the algorithm and its sampler's draw order; its source
    file), then the row's cells with the tests behind each (the site's Integrators section)."""
    from layerbvh_mitsuba.runtime.registry import PLUGINS, STANDS_IN_FOR  # local: Mitsuba (the checks need none)
    pages = {}
    for row in rows:
        names = [n.strip() for n in row.integrator.split(",")]
        out = [f"# `{row.integrator}`", ""]
        for name in names:
            plugin = STANDS_IN_FOR.get(name)
            if plugin is None:
                out += [f"`{name}` is a wrapper of stock Mitsuba's, run around ours (we mirror what it wraps).", ""]
                continue
            est = PLUGINS[plugin][1]
            src = Path(inspect.getsourcefile(est)).resolve().relative_to(ROOT)
            out += [f"Ours: `{plugin}` (`{est.__name__}`, `{src}`), standing in for stock `{name}`.", "",
                    _rst_to_md(est.__doc__ or ""), ""]
        out += ["## What the suite compares with stock", "", "| | claim | tests |", "|---|---|---|"]
        for key, title in COLUMNS:
            c = getattr(row, key)
            tests = "<br>".join(f"`{n}`" for n in c.nodes) or "–"
            out.append(f"| {title} | {c.text} | {tests} |")
        pages[f"integrators/{names[0]}.md"] = "\n".join(out) + "\n"
    return pages


def missing_nodes(rows=ROWS) -> list[str]:
    """The node ids the matrix names that pytest does not collect (pytest --collect-only)."""
    wanted = nodes(rows)
    files = sorted({n.split("::")[0] for n in wanted})
    p = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *files],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    collected = {ln.strip() for ln in p.stdout.splitlines() if "::" in ln}
    return [n for n in wanted if n not in collected]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--readme", action="store_true", help="splice the matrix into README.md (its status_matrix section)")
    p.add_argument("--check", action="store_true", help="exit 1 if a named node is not collected")
    args = p.parse_args(argv)
    if args.check:
        gone = missing_nodes()
        if gone:
            print("status_matrix: not collected: " + ", ".join(gone), file=sys.stderr)
            return 1
    md = markdown()
    if args.readme:
        atomic.splice_section(ROOT / "README.md", SECTION, md)
    else:
        print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
