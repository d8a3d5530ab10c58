"""Mutation check: does the test suite catch realistic bugs?

Copies the repository (tracked and untracked, not ignored files, as they are in the working
tree) to a temporary folder, then for each mutation in MUTATIONS, one at a time: replaces one
piece of text in one file of the copy (it must occur exactly once there, else the mutation is
"not applicable": the code moved on and the table must follow), runs the tests that should catch
it (pytest -x, in the copy: PYTHONPATH points `layerbvh` and `layerbvh_mitsuba` at the copied
packages, ahead of the editable install of the original checkout), prints one line, and puts
the file back. First the union of all listed tests runs on the unmutated copy (the baseline): a
test that fails there would "catch" anything.

A listed test whose process crashes (a signal, while pytest -v shows that test running) also catches
it: the suite stops there and names the test. Exit status 0 when every mutation is caught; 1 when
one is missed, not applicable or its run broke (a collection error or a timeout is not a catch); 2
when the baseline fails or the copy does not import its own packages.

    bash scripts/mutation_check.sh [--only NAME,...] [--list] [--dry-run] [--no-baseline] [--keep]
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from layerbvh import memmodel


@dataclass(frozen=True)
class Mutation:
    name: str
    what: str         # the bug, in words
    path: str         # the file it is made in, relative to the repository root
    old: str          # text that occurs exactly once in that file ...
    new: str          # ... and what replaces it
    tests: tuple      # pytest node ids that should catch it (run with -x, in this order)
    cpu_flag: str = ""  # a /proc/cpuinfo flag the bug needs to show (else skipped on this CPU, not missed)


MB = "tests/runtime/test_mitsuba_backend.py::"
SAME_SEED_LAYER = (MB + "test_same_seed_matches_stock[cbox-layer_sorted]",
                   MB + "test_same_seed_matches_stock[empty_box-layer_unsorted]")

# name, what, file, old -> new, the tests that should catch it.
MUTATIONS = (
    Mutation("pending_rays_dropped", "layer steps drop the rays still pending after the second step",
             "layerbvh/wavefront.py",
             "    while n_active > 0:\n",
             "    while n_active > 0 and stats.steps < 2:\n",
             SAME_SEED_LAYER + ("tests/engine/test_engine_hits.py::test_modes_agree_exactly[camera-bunny]",)),
    Mutation("first_exit_only", "exits beyond the first are ignored (the paper's bug): a step's other held exits "
             "are not written back",
             "layerbvh/walk.py",
             "            dr.scatter(spill.link, m.UInt32(loc_link[k]), top + k, keep)\n",
             "            held = m.UInt32(loc_link[k])\n"
             "            dr.scatter(spill.link, dr.select((held & 0x40000000) != 0, m.UInt32(0xFFFFFFFF), held), "
             "top + k, keep)  # EXIT_BIT -> POP\n",
             SAME_SEED_LAYER + ("tests/engine/test_engine_exact.py::"
                                "test_one_exit_rule_is_wrong_often_on_a_real_mesh",)),
    Mutation("spill_one_entry_more", "a wavefront step writes one entry more than a ray holds above its global "
             "stack (hits unchanged where the slot is never read: the kernel's store count must see it)",
             "layerbvh/walk.py",
             "            keep = ending & (m.UInt32(k) < nl)\n",
             "            keep = ending & (m.UInt32(k) <= nl) & (m.UInt32(k) < m.UInt32(cap))\n",
             ("tests/tools/test_locality.py::test_trace_follows_the_kernel_on_wide_trees[4]",)),
    Mutation("between_steps_forget_held_entries", "the model's between-step bytes leave out the entries each ray "
             "writes above its global stack",
             "layerbvh/steptraffic.py",
             "    kernel = n * 4 + left * record_bytes + pushed * ENTRY_BYTES\n",
             "    kernel = n * 4 + left * record_bytes\n",
             ("tests/tools/test_locality.py::test_between_step_bytes_are_what_the_kernel_stored[layer_sorted]",)),
    Mutation("tie_rule_flipped", "ties in t go to the larger primitive id",
             "layerbvh/walk.py",
             "    return prim < prim_best\n",
             "    return prim > prim_best\n",
             ("tests/engine/test_engine_layout.py::test_degenerate_meshes_build_and_trace[duplicated]",
              "tests/tools/test_stability.py::test_case[coplanar_overlap]")),
    Mutation("tie_culled", "a stack entry at exactly the closest hit's distance is culled (no rounding margin)",
             "layerbvh/walk.py",
             "(e_t <= t_best * FAR_SCALE)",
             "(e_t < t_best)",
             ("tests/engine/test_engine_layout.py::test_degenerate_meshes_build_and_trace[duplicated]",
              "tests/tools/test_stability.py::test_case[coplanar_overlap]")),
    Mutation("layer_path_skips_shadow_rays", "the integrator's layer path (wavefront loop) ignores its shadow rays",
             "plugin/runtime/estimators/path.py",
             "~queries.occluded(",
             "(not tr.megakernel) | ~queries.occluded(",
             SAME_SEED_LAYER),
    Mutation("batch_boundary_off_by_one", "each ray batch ends one ray early (the last ray of a batch is never traced)",
             "layerbvh/bvh.py",
             "min(n, start + self.batch_rays))",
             "min(n, start + self.batch_rays - 1))",
             ("tests/engine/test_engine_batches.py::test_batches_change_nothing_but_memory[layer_sorted]",
              "tests/runtime/test_large_pass.py::test_a_real_size_render_matches_stock")),
    Mutation("auto_reports_per_ray_runs_sorted", "auto decides as before but runs layer_sorted and reports per_ray",
             "layerbvh/bvh.py",
             "chosen = mode = ",
             'chosen, mode = "per_ray", "layer_sorted"; _decided = ',
             ("tests/engine/test_engine_batches.py::test_auto_runs_the_mode_it_reports",)),
    Mutation("finished_rays_not_sorted_last", "the sort key of a finished ray is its last treelet, not 'after every "
             "treelet' (the next step keeps finished rays and loses active ones)",
             "layerbvh/wavefront.py",
             "    keys = dr.select(done, finished_key, out.treelet)\n",
             "    keys = m.UInt32(out.treelet)\n",
             (MB + "test_same_seed_matches_stock[cbox-layer_sorted]",
              "tests/engine/test_engine_hits.py::test_modes_agree_exactly[incoherent-bunny]")),
    Mutation("tail_step_not_counted", "the per-ray tail is not counted as a step in the statistics",
             "layerbvh/wavefront.py",
             "            stats.tail_rays = n_active\n            stats.steps += 1\n",
             "            stats.tail_rays = n_active\n",
             ("tests/engine/test_engine_layout.py::test_step_statistics",)),
    Mutation("layer_modes_fall_back_to_per_ray", "the integrator's closest-hit queries run per_ray whatever the "
             "traversal (same hits, so the same image: only the statistics can tell)",
             "plugin/runtime/adapter.py",
             "self.bvh.trace(ray.o, ray.d, ray.maxt, mode=self.traversal,",
             'self.bvh.trace(ray.o, ray.d, ray.maxt, mode="per_ray" if self.traversal.startswith("layer") '
             'else self.traversal,',
             SAME_SEED_LAYER),
    Mutation("stability_on_one_treelet", "the stability suite's image cases run at the default treelet height "
             "(one treelet: layer_sorted cannot differ from per_ray)",
             "plugin/tools/stability/image_cases.py",
             "LAYER_HEIGHT = 2\n",
             "LAYER_HEIGHT = 8\n",
             ("tests/tools/test_stability.py::test_case[dielectric_ior_1.5]",)),
    Mutation("scale_referee_sides_swapped", "the extreme-scale referee names stock where ours matches it",
             "plugin/ab/referee.py",
             'else "ours" if ok_ours else "stock" if ok_stock',
             'else "stock" if ok_ours else "ours" if ok_stock',
             ("tests/tools/test_stability.py::test_the_scale_referee_names_the_side_that_matches",)),
    Mutation("scale_referee_camera_unscaled", "the extreme-scale scene keeps its camera at unit distance at every "
             "scale (the referee must see a scene that changed)",
             "plugin/tools/stability/scale_cases.py",
             '"origin": ", ".join(num(c * scale)',
             '"origin": ", ".join(num(c)',
             ("tests/tools/test_stability.py::test_case[extreme_scales]",)),
    Mutation("face_normals_unflipped", "the repaired normal of a shape with flip_normals points the other way",
             "plugin/runtime/extreme_scale.py",
             "-1.0 if s.is_mesh() and s.has_flipped_normals() else 1.0",
             "1.0",
             ("tests/runtime/test_extreme_scale.py::test_the_face_normal_table_is_mitsubas_normal_where_mitsubas_is_whole",)),
    Mutation("far_units_off", "triangles with coordinates past FAR_COORD are tested in plain units (their edge "
             "functions overflow at 1e18)",
             "layerbvh/geometry.py",
             "FAR_UNIT = 2.0 ** -80\n",
             "FAR_UNIT = 1.0\n",
             ("tests/tools/test_stability.py::test_case[extreme_scales]",)),
    Mutation("shadow_rays_not_rebuilt", "a far scene's shadow rays are Mitsuba's, lost past float32 range",
             "plugin/runtime/adapter.py",
             "        if self.far or self.tiny:\n",
             "        if self.tiny:\n",
             ("tests/tools/test_stability.py::test_case[extreme_scales]",)),
    Mutation("referee_clip_planes_kept", "the referee rescales the scene but leaves the camera's clip planes "
             "at the far scale (its image is empty)",
             "plugin/ab/referee.py",
             "                p[field[clip]] = p[field[clip]] * k\n",
             "                p[field[clip]] = p[field[clip]]\n",
             ("tests/tools/test_referee.py::test_the_rescaled_scene_is_the_scene_at_unit_size",
              "tests/tools/test_referee.py::test_a_scene_at_1e12_names_ours_as_the_side_that_matches_the_referee")),
    Mutation("referee_media_rescaled", "the referee rescales a scene with a medium as if its densities had no unit",
             "plugin/ab/referee.py",
             'if "Medium" in kind or "Volume" in kind:',
             'if False:',
             ("tests/tools/test_referee.py::test_what_cannot_be_rescaled_is_named",)),
    Mutation("tiny_scene_offsets_stock", "a tiny scene's rays keep stock's absolute offset floor (9e-5, 90 times the "
             "scene at 1e-6)",
             "plugin/runtime/adapter.py",
             "        self.tiny = extreme_scale.tiny_unit(scene)\n",
             "        self.tiny = None\n",
             ("tests/tools/test_stability.py::test_case[extreme_scales]",)),
    Mutation("tiny_offset_floor_one", "the unit-size offset keeps 1 as its floor",
             "plugin/runtime/extreme_scale.py",
             "    mag = (unit + dr.maximum(",
             "    mag = (1.0 + dr.maximum(",
             ("tests/runtime/test_extreme_scale.py::test_a_tiny_scene_offsets_its_rays_as_the_scene_at_unit_size",)),
    Mutation("status_matrix_claim_renamed", "a status-matrix cell names a test that does not exist",
             "plugin/tools/status_matrix.py",
             '(R + "test_depth.py::test_depth_matches_stock_depth_at_the_same_seed[cbox-per_ray]",)',
             '(R + "test_depth.py::test_depth_matches_stock_depth_at_the_same_seed[cbox-layer_sorted]",)',
             ("tests/tools/test_status_matrix.py::test_every_named_test_is_collected",)),
    Mutation("alias_copies", "the entry stack's write alias is a copy (what a Dr.Jit upgrade that copies in "
             "import_tensor would do)",
             "layerbvh/wavefront.py",
             "    return dr.detail.import_tensor(a, False).array\n",
             "    return type(a)(dr.detail.import_tensor(a, False).array.numpy().copy())\n",
             ("tests/engine/test_drjit_private_api.py::test_import_tensor_aliases_the_memory_of_an_evaluated_array",)),
    Mutation("docs_link_broken", "a README link points at a page that moved",
             "README.md",
             "| [Python API](docs/api.md) |",
             "| [Python API](docs/python_api.md) |",
             ("tests/tools/test_docs.py::test_every_relative_link_resolves",)),
    Mutation("census_literals_kept", "the kernel census groups kernels by their whole IR (literals kept), so "
             "no literal family is ever found",
             "layerbvh/kernel_census.py",
             'hashlib.blake2b(_LITERAL.sub("#", ir).encode()',
             'hashlib.blake2b(ir.encode()',
             ("tests/engine/test_kernel_census.py::test_the_census_records_compiles_and_groups_literal_variants",)),
    Mutation("site_links_unmoved", "the documentation site keeps the README's GitHub links (docs/...), which "
             "lead nowhere in the site",
             "scripts/mkdocs_hooks.py",
             'new = target[len("docs/"):] if target.startswith("docs/") else TOP.get(target, target)',
             'new = target',
             ("tests/tools/test_docs.py::test_the_site_builds_strict_with_every_page_and_the_cli",)),
    Mutation("frozen_step_allocates", "a frozen wavefront step allocates its state records itself (replayed at "
             "the size it was recorded at, whatever the step's lanes)",
             "layerbvh/wavefront.py",
             "rec_out, cap_local, finished_key, **kw)",
             "None, cap_local, finished_key, **kw)",
             ("tests/engine/test_engine_frozen.py::test_frozen_steps_return_the_unfrozen_hits_and_work_at_every_width",)),
    Mutation("frozen_step_collects", "the frozen steps do not hold Python's cycle collector (a Mitsuba scene "
             "freed inside a frozen step's recording aborts the process)",
             "layerbvh/wavefront.py",
             "from .collector import collector_held\n",
             "from contextlib import nullcontext as collector_held\n",
             ("tests/runtime/test_frozen_recording.py::"
              "test_a_scene_freed_by_the_cycle_collector_never_lands_in_a_frozen_recording",)),
    Mutation("children_class_per_call", "scene_geometry._children makes its callback class per call (a reference "
             "cycle holding the scene's objects until the collector runs)",
             "plugin/runtime/scene_geometry.py",
             "    if variant not in _OBJECTS_CALLBACK:",
             "    if True:",
             ("tests/runtime/test_frozen_recording.py::test_reading_a_scenes_children_leaves_no_cycle_garbage",)),
    Mutation("t_upper_common_stop", "t_upper iterates every element until all have converged (40 tail "
             "evaluations of the whole array where its elements need about 5)",
             "plugin/ab/hypotheses.py",
             "            go = go[~done]\n",
             "            go = go if not done.all() else go[:0]\n",
             ("tests/tools/test_hypotheses.py::test_t_quantiles_over_a_whole_grid_of_degrees_of_freedom",)),
    Mutation("t_upper_step_stop_only", "t_upper stops an element only on a small step (far in the tail the "
             "rounding keeps the steps large: every such element runs to the cap)",
             "plugin/ab/hypotheses.py",
             " | solved\n",
             "\n",
             ("tests/tools/test_hypotheses.py::test_t_quantiles_over_a_whole_grid_of_degrees_of_freedom",)),
    Mutation("t_upper_small_bracket", "t_upper's bracket tops at 1e4 (at df 1 a Bonferroni share of alpha "
             "needs t ~ 3e8: the quantile returned is the bracket's top)",
             "plugin/ab/hypotheses.py",
             "T_MAX = 1e12 ",
             "T_MAX = 1e4 ",
             ("tests/tools/test_hypotheses.py::test_t_quantiles_over_a_whole_grid_of_degrees_of_freedom",)),
    Mutation("census_keeps_callee_names", "the kernel census's families keep the names of called functions (a "
             "literal inside a virtual call's target then splits the family)",
             "layerbvh/kernel_census.py",
             'r"(drjit|func)_[0-9a-f]{32}|',
             'r"drjit_[0-9a-f]{32}|',
             ("tests/engine/test_kernel_census.py::test_a_literal_inside_a_called_function_keeps_the_family",)),
    Mutation("frozen_step_one_recording", "the frozen step keeps one recording, so every other batch shape traces "
             "the walk again",
             "layerbvh/wavefront.py",
             "_STEP = dr.freeze(_frozen_step, limit=32, warn_after=_NO_WARNING, state_fn=_configuration)",
             "_STEP = dr.freeze(_frozen_step, limit=1, warn_after=_NO_WARNING, state_fn=_configuration)",
             ("tests/engine/test_engine_frozen.py::test_frozen_steps_return_the_unfrozen_hits_and_work_at_every_width",)),
    Mutation("frozen_key_left_to_drjit", "the frozen step's key is left to dr.freeze's own traversal, which misses "
             "a changed any_hit (shared Python objects are visited once)",
             "layerbvh/wavefront.py",
             'return (f"{lay.depth}/{lay.height}/',
             'return ("",) or (f"{lay.depth}/{lay.height}/',
             ("tests/engine/test_engine_frozen.py::test_frozen_steps_return_the_unfrozen_hits_and_work_at_every_width",)),
    Mutation("forward_clears_interior", "the wavefront loop's forward push clears interior gradients (the "
             "texture's texel-derived array reaches the texels at the first vertex only)",
             "plugin/runtime/estimators/replay.py",
             "flags = dr.ADFlag.Default if megakernel else dr.ADFlag.ClearEdges",
             "flags = dr.ADFlag.Default if megakernel else dr.ADFlag.ClearEdges | dr.ADFlag.ClearInterior",
             ("tests/runtime/test_prb.py::test_a_textured_area_emitter_differentiates_as_stock_in_the_wavefront_loop",)),
    Mutation("backward_clears_edges", "the wavefront loop's backward push clears the edges it crosses (the "
             "texels' edge to the texture is gone after the first vertex)",
             "plugin/runtime/estimators/replay.py",
             "flags=dr.ADFlag.Default if megakernel else dr.ADFlag.ClearVertices)",
             "flags=dr.ADFlag.Default)",
             ("tests/runtime/test_prb.py::test_a_textured_area_emitter_differentiates_as_stock_in_the_wavefront_loop",)),
    Mutation("report_field_renamed", "report.json calls the film size `res`: a user's script reading the "
             "documented `resolution` breaks",
             "plugin/ab/compare.py",
             '"resolution": list(self.resolution), "seed": s.seed,',
             '"res": list(self.resolution), "seed": s.seed,',
             ("tests/tools/test_cli.py::test_compare_writes_every_file",)),
    Mutation("integrator_page_without_algorithm", "an integrator's documentation page leaves out its estimator's "
             "docstring (the algorithm and its draw order)",
             "plugin/tools/status_matrix.py",
             '_rst_to_md(est.__doc__ or ""), ""]',
             '""]',
             ("tests/tools/test_status_matrix.py::test_every_mirrored_integrator_has_its_page",)),
    Mutation("mutation_page_empty", "the documentation's mutation table lists none of the mutations",
             "scripts/mkdocs_hooks.py",
             "    for m in mc.MUTATIONS:\n",
             "    for m in mc.MUTATIONS[:0]:\n",
             ("tests/tools/test_docs.py::test_the_site_builds_strict_with_every_page_and_the_cli",)),
    Mutation("early_verdict_uncounted_pixels", "the verdict's early 'differs' counts no independent pixel tests in "
             "(its thresholds laxer than the whole family's)",
             "plugin/ab/hypotheses.py",
             '"pixel": panels * w * h * channels}',
             '"pixel": 0}',
             ("tests/tools/test_hypotheses.py::test_the_planned_counts_are_what_the_independent_tests_make[film0-1]",)),
    Mutation("mis_weight_swapped", "the power heuristic weighs by the other strategy's pdf",
             "plugin/runtime/estimators/common.py",
             "w = a2 / (a2 + b2)",
             "w = b2 / (a2 + b2)",
             (MB + "test_same_seed_matches_stock[cbox-per_ray]",)),
    Mutation("z_test_without_repeats", "the independent-seed test takes a sample's variance for the variance of "
             "the pixel's mean (too wide: it loses its power)",
             "plugin/ab/hypotheses.py",
             "                va = _region_sums(_split(a.var, panels)[p] / a.n, labels, k)\n"
             "                vb = _region_sums(_split(b.var, panels)[p] / b.n, labels, k)\n",
             "                va = _region_sums(_split(a.var, panels)[p], labels, k)\n"
             "                vb = _region_sums(_split(b.var, panels)[p], labels, k)\n",
             (MB + "test_z_test_catches_a_2_percent_albedo_change",)),
    Mutation("edge_refinement_off", "the double-precision recomputation of unsure edge functions never runs "
             "(error bound 0)",
             "layerbvh/geometry.py",
             "EDGE_ERR = 16 * 2.0 ** -24\n",
             "EDGE_ERR = 0.0\n",
             ("tests/tools/test_stability.py::test_case[watertight_edges_vertices]",
              "tests/tools/test_stability.py::test_case[grazing_rays]",
              "tests/tools/test_stability.py::test_case[sliver_triangles]")),
    Mutation("auto_prepass_skipped", "auto decides during the render again (no pre-pass): a render whose kinds all "
             "go per_ray runs the wavefront loop",
             "plugin/runtime/driver.py",
             "        if None in modes():\n",
             "        if False:\n",
             ("tests/runtime/test_auto_scenes.py::test_per_ray_everywhere_renders_the_per_ray_megakernel",)),
    Mutation("verdict_always_agrees", "the verdict's statistical step is ignored: diverged same-seed paths always "
             "'agree within noise'",
             "plugin/ab/metrics.py",
             "    label = (DIFFERS if rejected else",
             "    label = (DIFFERS if False else",
             ("tests/tools/test_verdict.py::test_a_real_difference_differs[max_depth]",)),
    Mutation("replay_ignores_culling", "the locality replay takes every popped entry, however far (the kernel culls "
             "those beyond the closest hit): its trace no longer follows the kernel",
             "layerbvh/memtrace.py",
             "link = e_link if (active and e_t <= fst[s, F_T] * _FAR) else _POP",
             "link = e_link if active else _POP",
             ("tests/tools/test_locality.py::test_trace_follows_the_kernel[closest-camera-bunny]",)),
    Mutation("replay_never_sorts", "the locality replay's layer_sorted keeps the unsorted order between steps",
             "layerbvh/locality.py",
             'keep = np.argsort(keys, kind="stable")[:n_active - done] if sort else np.flatnonzero(keys != finished)',
             "keep = np.flatnonzero(keys != finished)",
             ("tests/tools/test_locality.py::test_sorting_must_cut_transactions",)),
    Mutation("coalesce_without_dedup", "coalescing counts a segment once per lane that touches it",
             "layerbvh/cachesim.py",
             "            if j > 0 and out[j - 1] == s:\n                continue\n",
             "",
             ("tests/engine/test_memmodel.py::test_coalesce_broadcast_is_one_segment",)),
    Mutation("store_leaves_line_clean", "the cache model's stores leave their line clean: nothing is ever written "
             "back",
             "layerbvh/cachesim.py",
             "        dirty[victim] = 1 if (write and k == 0) else 0\n",
             "        dirty[victim] = 0\n",
             ("tests/engine/test_memmodel.py::test_a_store_allocates_its_line_and_a_dirty_victim_is_written_back_once",)),
    Mutation("dirty_victim_dropped", "the cache model evicts a dirty line without writing it back",
             "layerbvh/cachesim.py",
             "        elif dirty[victim]:\n",
             "        elif False:\n",
             ("tests/engine/test_memmodel.py::test_a_store_stream_writes_back_every_line_the_caches_cannot_hold[True]",)),
    Mutation("replay_stores_load", "the locality replay hands its local-stack stores to the cache model as loads",
             "layerbvh/memtrace.py",
             "k in STORE_SITES",
             "False",
             ("tests/tools/test_locality.py::test_the_replays_stores_are_the_cache_models_write_misses",)),
    Mutation("replay_stores_no_state_records", "the locality replay's steps write no state record for the rays "
             "that go on",
             "layerbvh/memstores.py",
             "        if ist[s, I_DONE] == 0:\n            req_j[S_STATE_OUT] = position\n",
             "        if False:\n            req_j[S_STATE_OUT] = position\n",
             ("tests/tools/test_locality.py::test_trace_follows_the_kernel[closest-camera-bunny]",)),
    Mutation("cachegrind_reads_only", "the valgrind check compares read misses only: the model's stores get no "
             "verdict",
             "scripts/check_model_cachegrind.py",
             "            if any(r.get(model) is None or r.get(cg) is None for r in (p, s)):",
             "            if misses == \"writes\" or any(r.get(model) is None or r.get(cg) is None for r in (p, s)):",
             ("tests/tools/test_model_cachegrind.py::test_write_misses_get_verdicts_of_their_own",)),
    Mutation("ray_records_filled_first", "the ray records' array is filled with zeros before the kernel writes them "
             "(a memset pass over every record)",
             "layerbvh/state.py",
             "        rec = dr.empty(m.Float, n * self.STRIDE)\n",
             "        rec = dr.zeros(m.Float, n * self.STRIDE)\n",
             ("tests/engine/test_engine_kernels.py::test_ray_records_are_packed_by_one_kernel",)),
    Mutation("line_over_120_columns", "a line of 130 columns in a module off the ruff backlog",
             "layerbvh/cachesim.py",
             "EMPTY_TAG = -1  # line numbers are >= 0 because addresses are\n",
             "EMPTY_TAG = -1  # line numbers are >= 0 because addresses are"
             + " (and a comment that runs on)" * 3 + "\n",
             ("tests/tools/test_code_layout.py::test_lines_are_at_most_120_columns",)),
    Mutation("driver_methods_copied", "each integrator class gets copies of the driver's methods instead of "
             "inheriting them",
             "plugin/runtime/registry.py",
             'type(name, (driver,), {**names, "ESTIMATOR": estimator, "PLUGIN": plugin})',
             'type(name, (driver,), {**{k: v for k, v in vars(driver).items() if callable(v) and k != "__init__"}, '
             '**names, "ESTIMATOR": estimator, "PLUGIN": plugin})',
             ("tests/runtime/test_mitsuba_backend.py::test_every_integrator_is_a_subclass_of_the_one_driver_class",)),
    Mutation("replay_skips_setup_passes", "the locality replay leaves out the trace call's passes before its first "
             "kernel (the compaction, the records' packing, the results' fill)",
             "layerbvh/locality.py",
             "    for region, nbytes, write in passes if n else ():\n",
             "    for region, nbytes, write in ():\n",
             ("tests/tools/test_locality.py::test_two_warps_transactions_by_hand",)),
    Mutation("wide_drops_farthest_child", "a wide node pushes one entry fewer than it hits (the farthest hit child "
             "is dropped)",
             "layerbvh/walk.py",
             "n_push = dr.select(n_hit > 1, n_hit - 1, m.UInt32(0))",
             "n_push = dr.select(n_hit > 2, n_hit - 2, m.UInt32(0))",
             ("tests/engine/test_engine_wide.py::test_every_mode_returns_the_binary_per_ray_bits[camera-4]",)),
    Mutation("collapse_opens_smallest", "the collapse pulls up the child of smallest surface area",
             "layerbvh/collapse.py",
             "if left[c] >= 0 and area[c] > best_area:",
             "if left[c] >= 0 and (best < 0 or area[c] < best_area):",
             ("tests/engine/test_engine_wide.py::test_collapse_pulls_up_the_largest_children[4]",)),
    Mutation("boxes_not_widened", "child boxes are stored as built (a ray in a box's face plane misses it)",
             "layerbvh/relayout.py",
             "    lo_out = np.nextafter(b.lo, np.float32(-np.inf))\n"
             "    hi_out = np.nextafter(b.hi, np.float32(np.inf))\n",
             "    lo_out, hi_out = b.lo, b.hi\n",
             ("tests/tools/test_stability.py::test_case[axis_aligned_rays]",)),
    Mutation("collector_runs_mid_recording", "the render no longer pauses Python's garbage collector while Dr.Jit "
             "records it (issue 39: a dead scene's medium freed mid-recording aborts the process)",
             "layerbvh/collector.py",
             "            gc.disable()\n",
             "            pass\n",
             ("tests/runtime/test_held_instances.py::test_a_collection_during_recording_cannot_abort_the_render",
              "tests/runtime/test_frozen_recording.py::"
              "test_a_scene_freed_by_the_cycle_collector_never_lands_in_a_frozen_recording")),
    Mutation("slurm_controller_not_probed", "the sweep submits to SLURM without checking that a controller answers "
             "(issue 39: an internal error and a half-made output folder)",
             "plugin/tools/sweep/slurm.py",
             "    _find_controller()\n    return settings\n",
             "    return settings\n",
             ("tests/tools/test_slurm.py::test_an_unreachable_controller_gets_one_line",)),
    Mutation("held_entries_not_counted", "the entries a ray still holds at a step's end are written above its global "
             "stack, but the depth in its state record is not raised by them (issue 40's step design: they are lost)",
             "layerbvh/walk.py",
             "        out.sp = out.sp + nl\n",
             "        out.sp = out.sp + 0 * nl\n",
             ("tests/engine/test_engine_hits.py::test_modes_agree_exactly[camera-bunny]",)),
    Mutation("state_records_read_in_lane_order", "the next step reads the state records in the order the step "
             "before wrote them, not through the sort's permutation (issue 40: nothing else permutes the states)",
             "layerbvh/wavefront.py",
             "    s = StateRecords.read(m, rec, perm, instanced, words)\n",
             "    s = StateRecords.read(m, rec, dr.arange(m.UInt32, dr.width(perm)), instanced, words)\n",
             ("tests/engine/test_engine_hits.py::test_modes_agree_exactly[incoherent-bunny]",)),
    Mutation("kernel_reads_one_more_array", "a wavefront step looks up the treelet of every node entry it pops, "
             "its own pushes included (same hits, one more load per pop: the load-count check must see it)",
             "layerbvh/walk.py",
             "global_node = other & from_global & ~is_exit\n",
             "global_node = other & ~is_exit\n",
             ("tests/tools/test_locality.py::test_trace_follows_the_kernel[closest-camera-bunny]",)),
    Mutation("closer_hit_not_written", "a wavefront step does not write a closer hit's u and v to the results "
             "(they are no longer carried in the state: issue 40)",
             "layerbvh/walk.py",
             "for dst, src in ((results.t, t), (results.u, u), (results.v, v), (results.prim, prim)):",
             "for dst, src in ((results.t, t), (results.prim, prim)):",
             ("tests/engine/test_engine_hits.py::test_modes_agree_exactly[camera-bunny]",)),
    Mutation("numpy_mapped_unaligned", "numpy arrays go to Dr.Jit as they are (a kernel per alignment of its "
             "inputs: the suite compiles thousands of kernels more)",
             "layerbvh/backend.py",
             "return T(a) if dr.is_array_v(a) else T(aligned(np.asarray(a)))",
             "return T(a) if dr.is_array_v(a) else T(np.asarray(a))",
             ("tests/engine/test_engine_kernels.py::test_numpy_inputs_compile_one_kernel_whatever_their_alignment",)),
    Mutation("treelet_count_literal", "the finished rays' sort key enters the step kernel as a literal (a kernel "
             "per tree)",
             "layerbvh/wavefront.py",
             "finished_key = dr.opaque(m.UInt32, finished)",
             "finished_key = m.UInt32(finished)",
             ("tests/engine/test_engine_kernels.py::test_a_second_tree_compiles_no_new_kernel[layer_sorted]",)),
    Mutation("lazy_rays_per_column", "a caller's lazy rays are not evaluated together: each column the traversal "
             "gathers computes them again, in a kernel of its own",
             "layerbvh/inputs.py",
             "    dr.eval(o, d, tm, valid)\n    return RayBatch(o, d, tm, valid, on_device)",
             "    return RayBatch(o, d, tm, valid, on_device)",
             ("tests/engine/test_engine_kernels.py::test_lazy_rays_are_computed_in_one_kernel[layer_sorted]",)),
    Mutation("local_stack_per_depth", "a walk's local stack is sized to the tree's exact depth (a kernel per depth)",
             "layerbvh/wavefront.py",
             "return max(LOCAL_ROWS_MIN, 1 << (rows - 1).bit_length())",
             "return rows",
             ("tests/engine/test_engine_kernels.py::test_a_second_tree_compiles_no_new_kernel[per_ray]",)),
    Mutation("replay_wide_children_unsorted", "the locality replay takes a wide node's children in their stored "
             "order (the kernel sorts them by entry distance)",
             "layerbvh/memtrace.py",
             "    for p in range(net.shape[0]):\n",
             "    for p in range(0):\n",
             ("tests/tools/test_locality.py::test_trace_follows_the_kernel_on_wide_trees[4]",)),
    Mutation("step_cap_ignored", "a batch takes wavefront steps until its rays finish however many that is "
             "(the tail's step cap is never applied)",
             "layerbvh/wavefront.py",
             " or steps >= TAIL_STEPS\n",
             "\n",
             ("tests/engine/test_engine_hits.py::test_the_step_cap_hands_a_long_batch_to_the_tail",)),
    Mutation("gpu_report_stack_moves_as_setup", "the GPU report counts a kernel between a step and its sort (the "
             "H200 listings' stack moves) as set-up, so the between-step cost it lists is too small",
             "plugin/tools/bench/gpu_report.py",
             '                cur["between_ms"] += ms\n',
             '                cur["rest_ms"] += ms\n',
             ("tests/tools/test_gpu_check.py::test_a_launch_between_a_step_and_its_sort_is_counted_apart",)),
    Mutation("ptracer_bsdf_draws_in_written_order", "ptracer draws a BSDF sample's 1D before its 2D, as the call "
             "reads (stock's GCC-built wheel evaluates the arguments right to left): every light path after its "
             "first bounce differs",
             "plugin/runtime/estimators/ptracer.py",
             "            s1, s2 = draw_order.draws(sampler, active)  # (stock's order: see the class docstring)\n",
             "            s1 = sampler.next_1d(active)\n            s2 = sampler.next_2d(active)\n",
             ("tests/runtime/test_ptracer.py::test_ptracer_agrees_with_stock[cbox-per_ray]",)),
    Mutation("ptracer_sensor_never_occluded", "ptracer splats every vertex the sensor faces, blocked or not (its "
             "sensor connection's occlusion test is skipped)",
             "plugin/runtime/estimators/ptracer.py",
             "        active &= ~tr.queries.occluded(sensor_ray, active)\n",
             "        tr.queries.occluded(sensor_ray, active)\n",
             ("tests/runtime/test_ptracer.py::test_ptracer_agrees_with_stock[cbox-per_ray]",)),
    Mutation("adjoint_moments_per_sample", "the verdict's second step takes an adjoint integrator's per-render "
             "variance for a per-sample one (far too strict: equal estimators fail)",
             "plugin/ab/verdict.py",
             "    return Moments(v.mean(0), v.var(0, ddof=1), MOMENT_RENDERS, renders=v)\n",
             "    return Moments(v.mean(0), v.var(0, ddof=1), spp)\n",
             ("tests/runtime/test_ptracer.py::test_ptracer_statistical_step_catches_a_2_percent_albedo_change",)),
    Mutation("prb_forward_clears_parameter_gradients", "forward-mode replay in the wavefront loop uses Dr.Jit's "
             "default flags, which clear the parameters' gradients after the first vertex",
             "plugin/runtime/estimators/replay.py",
             "    flags = dr.ADFlag.Default if megakernel else dr.ADFlag.ClearEdges\n",
             "    flags = dr.ADFlag.Default\n",
             ("tests/runtime/test_prb.py::test_gradients_same_seed_as_stock[prb-cbox-layer_sorted]",)),
    Mutation("prb_emitter_visibility_ignored", "prb's emitter samples count whether or not our shadow query finds "
             "them occluded",
             "plugin/runtime/estimators/common.py",
             "        weight = dr.select(occluded, 0, weight)\n        ds.pdf = dr.select(occluded, 0, ds.pdf)\n",
             "",
             ("tests/runtime/test_prb.py::test_primal_same_seed_as_stock[prb-bunny_box-per_ray]",)),
    Mutation("prb_reflection_not_reattached", "prb's replay pushes emission and emitter samples but not the "
             "reflected rest of the path (Lr_ind left out)",
             "plugin/runtime/estimators/prb.py",
             "                dL = propagate(mode, dL, Le + Lr_dir + Lr_ind, s.active, tr.megakernel)\n",
             "                dL = propagate(mode, dL, Le + Lr_dir, s.active, tr.megakernel)\n",
             ("tests/runtime/test_prb.py::test_gradients_same_seed_as_stock[prb-bunny_box-per_ray]",)),
    Mutation("gradient_step_not_paired", "the gradient verdict's second step renders ours at other seeds than "
             "stock's (Welch's power, not the pairs'): at GRAD_SAMPLES a parameter 2% off passes",
             "plugin/ab/gradient.py",
             "            side[name] = _moments([gradients(mi, sc, integ, key, spp, "
             "PAIR_SEED * MOMENT_RENDERS + r, forward)\n",
             "            side[name] = _moments([gradients(mi, sc, integ, key, spp, "
             "(PAIR_SEED + (name == 'ours')) * MOMENT_RENDERS + r, forward)\n",
             ("tests/runtime/test_prb.py::test_gradient_statistical_step_and_its_negative_control",)),
    Mutation("prbvolpath_nee_not_replayed", "prbvolpath's replay skips the emitter sample's transmittance "
             "derivatives",
             "plugin/runtime/estimators/prbvolpath.py",
             "                self.sample_emitter(*args, nee_sampler, mode, adj_emitted=contrib, dL=dL)\n",
             "",
             ("tests/runtime/test_prb.py::test_prbvolpath_in_media_same_seed_and_backward",)),
    Mutation("differentiable_render_not_held", "a differentiable render pauses the collector only inside each "
             "`sample`, not across Mitsuba's render_forward/render_backward (Dr.Jit then aborts)",
             "plugin/runtime/registry.py",
             '                     "render_forward": driver.render_forward_held,\n'
             '                     "render_backward": driver.render_backward_held}\n',
             "}\n",
             ("tests/runtime/test_held_instances.py::test_a_differentiable_render_holds_the_collector_across_forward_and_backward",
              "tests/runtime/test_prb.py::test_gradients_same_seed_as_stock[prb-cbox-layer_sorted]")),
    Mutation("cachegrind_disturbed_run_tabulated", "the valgrind check tabulates a run whose N-ray region counted "
             "more events than its 2N-ray one (negative misses per ray)",
             "scripts/check_model_cachegrind.py",
             '    if min(out["D1"], out["LL"], out["instructions"]) < 0:\n',
             "    if False:\n",
             ("tests/tools/test_model_cachegrind.py::test_a_disturbed_measurement_is_refused",)),
    Mutation("walk_state_holds_the_tree", "a walk's loop state takes the tree, the state and the stacks it only "
             "reads (Dr.Jit traces the body twice to drop them)",
             "layerbvh/walk.py",
             "    lay, s, stack, spill, results = (Held.of(x) for x in (lay, s, stack, spill, results))\n",
             "",
             ("tests/engine/test_engine_kernels.py::test_a_walk_traces_its_loop_once[per_ray-2-False]",)),
    Mutation("walk_state_keeps_idle_counters", "a walk's loop state takes the work counters a walk without "
             "statistics never changes",
             "layerbvh/walk.py",
             '    n_inner, n_leaf, n_tri, n_iter, n_root = (Held.unless(counting["inner"], x)\n',
             '    n_inner, n_leaf, n_tri, n_iter, n_root = (Held.unless(True, x)\n',
             ("tests/engine/test_engine_kernels.py::test_a_walk_traces_its_loop_once[layer_sorted-4-True]",)),
    Mutation("numba_cache_never_refreshed", "a module's numba cache is kept whatever its dependencies' sources "
             "(an edited constant served stale)",
             "layerbvh/numba_cache.py",
             "        if stamp.exists() and stamp.read_text() == digest:\n",
             "        if stamp.exists():\n",
             ("tests/engine/test_numba_cache.py::test_an_edited_dependency_is_compiled_again",)),
    Mutation("model_note_ignores_verdict", "a locality verdict's note counts the model as agreeing with valgrind "
             "where only the ratio agrees (the verdict the other one)",
             "plugin/tools/bench/model_checked.py",
             'append(bool(v["ratio_agrees"] and v["verdict_agrees"]))',
             'append(bool(v["ratio_agrees"]))',
             ("tests/tools/test_locality.py::test_a_verdict_says_what_its_model_was_checked_against",)),
    Mutation("cachegrind_disagreement_passes", "the valgrind check exits 0 where the model's sorted / per_ray "
             "verdict is the other one (issue 57 item 5)",
             "scripts/check_model_cachegrind.py",
             '           if not (v["ratio_agrees"] and v["verdict_agrees"])]',
             '           if not v["ratio_agrees"]]',
             ("tests/tools/test_model_cachegrind.py::test_a_disagreement_with_valgrind_fails_the_check",)),
    Mutation("volpathmis_forgets_nee_after_scattering", "volpathmis keeps the old p_over_f_nee after a real "
             "collision in a medium (the shared walk's strategy hook does nothing)",
             "plugin/runtime/estimators/volpathmis.py",
             "        return Ratios(w.p_over_f, self.W.select(scattered, w.p_over_f, w.p_over_f_nee), "
             "w.last_event_was_null)",
             "        return w",
             ("tests/runtime/test_volpath.py::test_mitsuba_volpathmis_scenes_match_stock_at_the_same_seed[test_homo_spectral_sigmat]",
              "tests/runtime/test_media_reference.py::test_volpathmis_passes_mitsubas_reference_test[test_hetero_spectral_sigmat]")),
    Mutation("volpath_albedo_lost", "volpath's real collision in a medium of spectral extinction weighs the "
             "throughput by sigma_s alone (its strategy's real_collision drops the real-collision probability)",
             "plugin/runtime/estimators/volpath.py",
             "        throughput = dr.select(spectral, _scaled(w.throughput, mei.sigma_s\n"
             "                               / dr.mean(mei.sigma_t / mei.combined_extinction, axis=0)), "
             "w.throughput)\n",
             "        throughput = dr.select(spectral, _scaled(w.throughput, mei.sigma_s), "
             "w.throughput)\n",
             ("tests/runtime/test_media_reference.py::test_ours_passes_mitsubas_reference_test[test_hetero_sigmat]",)),
    Mutation("plugin_imports_the_engine", "the pytest plugin imports the engine (and with it Dr.Jit and numba) when "
             "pytest starts",
             "plugin/pytest_plugin.py",
             "from layerbvh_mitsuba import atomic\n",
             "from layerbvh_mitsuba import atomic\nimport layerbvh  # noqa: F401\n",
             ("tests/tools/test_pytest_plugin.py::test_the_plugin_costs_nothing_until_used",)),
    Mutation("registration_needs_mitsuba_first", "importing the package before Mitsuba registers nothing (no "
             "finder waits for Mitsuba's import)",
             "plugin/__init__.py",
             "    sys.meta_path.insert(0, _AfterMitsuba())",
             "    pass",
             ("tests/runtime/test_mitsuba_backend.py::test_registered_for_every_variant_set_later[layerbvh_mitsuba]",)),
    Mutation("cachegrind_check_model_over_2n", "the cachegrind check spreads the model's extra misses over 2N rays "
             "where valgrind's are spread over N",
             "scripts/check_model_cachegrind.py",
             '        return float(got[2 * n][level][sites].sum() - got[n][level][sites].sum()) / n\n',
             '        return float(got[2 * n][level][sites].sum() - got[n][level][sites].sum()) / (2 * n)\n',
             ("tests/tools/test_model_cachegrind.py::test_the_model_misses_what_valgrind_misses_on_the_per_ray_kernel",)),
    Mutation("polarized_throughput_all_ones", "a path's starting throughput fills every Mueller-matrix entry with 1 "
             "(dr.full) instead of the identity",
             "plugin/runtime/estimators/common.py",
             "    return mi.Spectrum(dr.full(mi.Float, 1, n))\n",
             "    return dr.full(mi.Spectrum, 1, n)\n",
             ("tests/runtime/test_polarized.py::test_stokes_around_ours_equals_stock_in_all_four_stokes_components[stokes-per_ray]",)),
    Mutation("path_bsdf_weight_in_local_frame", "path's BSDF sample weight stays in the BSDF's local Stokes frames "
             "(no to_world_mueller)",
             "plugin/runtime/estimators/path.py",
             "        bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi)\n",
             "",
             ("tests/runtime/test_polarized.py::test_stokes_around_ours_equals_stock_in_all_four_stokes_components[stokes-per_ray]",)),
    Mutation("stokes_wrapper_not_read", "a stokes scene's wrapper is matched against to_string's name, which holds "
             "nothing of what stokes wraps (the scene is then refused)",
             "plugin/ab/scene_integrator.py",
             "    if wrapper is not None and wrapper.loaded_name != name:\n",
             "    if wrapper is not None and wrapper.name != name:\n",
             ("tests/runtime/test_polarized.py::test_a_stokes_scene_is_read_as_stokes_around_its_estimator",)),
    Mutation("stokes_compared_on_rgb_only", "compare judges a stokes render on its RGB alone, as an aov's (S0-S3 "
             "unjudged)",
             "plugin/ab/compare.py",
             '    stokes = path.wrapper is not None and path.wrapper.type == "stokes"\n',
             "    stokes = False\n",
             ("tests/runtime/test_polarized.py::test_compare_judges_the_five_stokes_panels",)),
    Mutation("stokes_statistical_rgb_only", "the independent-seed step of a stokes render tests its RGB alone",
             "plugin/ab/verdict.py",
             "    judged = metrics.stokes_panels if _stokes(integrator) else (lambda img: img[..., :3])\n",
             "    judged = lambda img: img[..., :3]  # noqa: E731\n",
             ("tests/runtime/test_polarized.py::test_compare_judges_the_five_stokes_panels",)),
    Mutation("render_exr_channels_unnamed", "`layerbvh render` writes a wrapper's channels unnamed (ch00, ...)",
             "plugin/cli.py",
             "    write_exr(args.output, img, render_channels(rendered, img.shape[-1] if img.ndim == 3 else 1))\n",
             "    write_exr(args.output, img)\n",
             ("tests/runtime/test_polarized.py::test_render_writes_the_stokes_channels_under_stocks_names",)),
    Mutation("third_party_integrator_ignored", "compare renders the scene's own integrator whatever "
             "CompareSettings.integrator (a SCENE@INTEGRATOR row) asks for",
             "plugin/ab/compare.py",
             "    chosen = None if s.integrator is None else "
             "_stage(STOCK, \"setup\", lambda: load_integrator(mi, s.integrator))\n",
             "    chosen = None\n",
             ("tests/tools/test_third_party.py::test_table_has_a_verdict_per_scene_and_names_refused_plugins",)),
    Mutation("scene_sample_count_zero_rendered", "a scene whose sampler has sample_count 0 (no --spp) is rendered: "
             "the process dies of SIGFPE (issue 56)",
             "plugin/ab/render.py",
             "    if spp < 1:\n        raise UserError(f\"the scene's sampler has sample_count {spp}; "
             "give --spp N or a sample_count >= 1\")\n",
             "",
             ("tests/tools/test_cli.py::test_legal_scene_numbers_and_seeds_a_sampler_cannot_take_are_one_line",)),
    Mutation("pass_seed_overflows", "pass seeds seed x 7919 + k without the modulo: a Unix time as the seed "
             "overflows the sampler's 32 bits (issue 56)",
             "plugin/ab/render.py",
             "    return seed if passes == 1 else (seed * 7919 + k) % (SEED_MAX + 1)\n",
             "    return seed if passes == 1 else seed * 7919 + k\n",
             ("tests/tools/test_cli.py::test_legal_scene_numbers_and_seeds_a_sampler_cannot_take_are_one_line",)),
    Mutation("sweep_out_not_checked", "sweep writes into whatever --out names: a folder of the user's own "
             "index.html, results.csv and summary.md is overwritten (issue 56)",
             "plugin/tools/sweep/grid.py",
             "    problem = atomic.check_output_folder(args.out, (RUNS_FILE, JOB_SCRIPT))\n",
             "    problem = None\n",
             ("tests/tools/test_sweep.py::test_bad_sweep_input_gives_one_line_and_writes_nothing",)),
    Mutation("lfs_texture_not_named", "a scene whose texture is a Git LFS pointer fails with Mitsuba's "
             "'Bitmap: Unknown file format!' alone, naming no file (issue 56)",
             "plugin/ab/render.py",
             "        named = _file_behind(str(e))\n",
             "        named = ''\n",
             ("tests/tools/test_cli.py::test_legal_scene_numbers_and_seeds_a_sampler_cannot_take_are_one_line",)),
    Mutation("zero_scale_instance_kept", "an instance scaled to zero is handed to the engine (refused as "
             "singular), where stock renders it as absent (issue 56)",
             "plugin/runtime/scene_geometry.py",
             "        if np.linalg.matrix_rank(m[:3, :3]) < 3:\n",
             "        if False:\n",
             ("tests/runtime/test_instancing.py::test_an_instance_scaled_to_zero_renders_as_stock_renders_it",)),
    Mutation("sigterm_not_handled", "SIGTERM keeps Python's default (the process dies where it is: Dask's "
             "processes warn of leaked semaphores, no line, exit -15) (issue 56)",
             "plugin/cli.py",
             "        old = signal.signal(signal.SIGTERM, _on_sigterm)\n",
             "        old = signal.getsignal(signal.SIGTERM)\n",
             ("tests/tools/test_sweep.py::test_sigterm_stops_a_sweep_as_ctrl_c_does",)),
    Mutation("draw_order_hard_coded", "a BSDF sample's numbers drawn in GCC's order whatever the probe of the "
             "wheel says (issue 55: another compiler's wheel would break same-seed comparisons silently)",
             "plugin/runtime/draw_order.py",
             "    if bsdf_2d_first():\n",
             "    if True:\n",
             ("tests/runtime/test_direct.py::test_the_bsdf_draw_order_is_probed_from_the_wheel",)),
    Mutation("draw_order_probe_inverted", "the probe reads the BSDF's two numbers the wrong way round",
             "plugin/runtime/draw_order.py",
             "    return two < one\n",
             "    return two > one\n",
             ("tests/runtime/test_direct.py::test_the_bsdf_draw_order_is_probed_from_the_wheel",)),
    Mutation("cachegrind_not_measured_again", "a disturbed cachegrind measurement stops the check at once, as "
             "one did on a loaded machine (issue 56)",
             "scripts/check_model_cachegrind.py",
             "ATTEMPTS = 3  # measurements of a (D1, n) pair before a disturbed one stops the check\n",
             "ATTEMPTS = 1  # measurements of a (D1, n) pair before a disturbed one stops the check\n",
             ("tests/tools/test_model_cachegrind.py::test_a_disturbed_measurement_is_measured_again",)),
    Mutation("ptracer_samples_per_pass_zero_rendered", "a ptracer scene with samples_per_pass 0 is rendered: "
             "stock's render divides by it and the process dies of SIGFPE (issue 56)",
             "plugin/ab/scene_integrator.py",
             "        if props[\"samples_per_pass\"] < 1:  # (stock's render divides by it: SIGFPE, issue 56)\n",
             "        if False:\n",
             ("tests/tools/test_cli.py::test_legal_scene_numbers_and_seeds_a_sampler_cannot_take_are_one_line",)),
    Mutation("gradient_stock_side_taken_for_ours", "a gradient step given stock's earlier renders takes them for "
             "ours' side as well (the negative control then compares stock with itself)",
             "plugin/ab/gradient.py",
             '    side = {} if stock_side is None else {"stock": stock_side}\n',
             '    side = {} if stock_side is None else {"stock": stock_side, "ours": stock_side}\n',
             ("tests/runtime/test_prb.py::test_gradient_statistical_step_and_its_negative_control",)),
    Mutation("llvm_isa_env_ignored", "LAYERBVH_LLVM_ISA is read but not applied: the kernels compile for the "
             "CPU's own ISA, so a test meant to run as on an AVX2 CPU runs as on this one (issue 64)",
             "layerbvh/backend.py",
             "            set_llvm_isa(isa)\n",
             "            LLVM_ISAS[isa]\n",
             ("tests/engine/test_engine_isa.py::test_avx2_kernels_trace_the_same_hits",), cpu_flag="avx512f"),
    Mutation("llvm_avx2_keeps_avx512", "LAYERBVH_LLVM_ISA=avx2 narrows the packets to 8 lanes but leaves the "
             "AVX-512 features on (another rounding than an AVX2 CPU's)",
             "layerbvh/backend.py",
             "    if isa == \"avx2\":\n        have = ",
             "    if False:\n        have = ",
             ("tests/engine/test_engine_isa.py::test_avx2_kernels_trace_the_same_hits",), cpu_flag="avx512f"),
    Mutation("verdict_without_paired_tests", "the verdict leaves out the paired same-seed tests: an \"agrees\" "
             "rules out only what the independent-seed film sees (issue 55)",
             "plugin/ab/verdict.py",
             "        paired = hypotheses.paired(stock_img, ours_img, reach,",
             "        paired = [] and hypotheses.paired(stock_img, ours_img, reach,",
             ("tests/tools/test_verdict.py::test_diverged_paths_of_a_full_depth_scene_agree_and_the_report_says_why",)),
    Mutation("paired_variance_ignores_shared_samples", "the paired test's variance leaves out the covariance of "
             "pixels that share samples through the film's filter (too narrow: false alarms)",
             "plugin/ab/hypotheses.py",
             "            se.append(np.sqrt(_hac(d, labels, k, reach)))\n",
             "            se.append(np.sqrt(_hac(d, labels, k, 0)))\n",
             ("tests/tools/test_hypotheses.py::test_paired_false_alarms_stay_below_alpha[1]",)),
    Mutation("correction_per_test_not_per_family", "each test gets its level's whole share of alpha instead of "
             "a part of it (no correction for the number of tests: false alarms)",
             "plugin/ab/hypotheses.py",
             "        return ALPHA * SHARES[level] / max(1, self.counts[level])\n",
             "        return ALPHA * SHARES[level]\n",
             ("tests/tools/test_hypotheses.py::test_one_correction_over_every_test",)),
    Mutation("volpath_albedo_2_percent_low", "ours' volpath scatters with 98% of the medium's albedo: a 2% "
             "bias that the verdict at the media test's own settings (16 spp) must see (issue 55)",
             "plugin/runtime/estimators/volpath.py",
             "        throughput = dr.select(spectral, _scaled(w.throughput, mei.sigma_s\n"
             "                               / dr.mean(mei.sigma_t / mei.combined_extinction, axis=0)), "
             "w.throughput)\n"
             "        throughput = dr.select(plain, _scaled(throughput, mei.sigma_s / mei.sigma_t), throughput)\n",
             "        throughput = dr.select(spectral, _scaled(w.throughput, 0.98 * mei.sigma_s\n"
             "                               / dr.mean(mei.sigma_t / mei.combined_extinction, axis=0)), "
             "w.throughput)\n"
             "        throughput = dr.select(plain, _scaled(throughput, 0.98 * mei.sigma_s / mei.sigma_t), "
             "throughput)\n",
             ("tests/runtime/test_volpath.py::test_heterogeneous_media_agree_with_stock_within_noise",)),
    Mutation("prb_replay_without_area_jacobian", "the replay leaves out the solid-angle to area Jacobian of a "
             "moving vertex: derivatives with respect to geometry are wrong (issue 55)",
             "plugin/runtime/estimators/replay.py",
             "        return L * dr.relative_grad(f) * dr.relative_grad(J)\n",
             "        return L * dr.relative_grad(f)\n",
             ("tests/runtime/test_prb.py::test_gradients_same_seed_as_stock[prb-bunny_box-per_ray]",)),
    Mutation("prb_replay_direction_not_turned", "the replay keeps the sampled direction fixed where a vertex "
             "moves (the cosine and BSDF do not turn with the geometry)",
             "plugin/runtime/estimators/replay.py",
             "        wo = si.to_local(dr.replace_grad(ray_next.d, toward))\n",
             "        wo = si.to_local(ray_next.d)\n",
             ("tests/runtime/test_prb.py::test_gradients_same_seed_as_stock[prb-bunny_box-per_ray]",)),
    Mutation("check_ignores_asked_mde", "a pytest check given mde= runs once at its spp and passes whatever its "
             "verdict's MDE (issue 55)",
             "plugin/testing.py",
             "    if mde is None:\n        return run_one(",
             "    if True:\n        return run_one(",
             ("tests/tools/test_verdict.py::test_a_check_asked_for_an_mde_takes_the_samples_it_needs",)),
)


def copy_repository(src: Path, dst: Path) -> int:
    """Tracked and untracked (not ignored) files of `src` as they are in the working tree, with
    their times (numba's cache checks them); numba's compiled kernels (ignored __pycache__
    files) too, so the copy does not recompile the builder. Returns the number of files."""
    out = subprocess.run(["git", "-C", str(src), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         capture_output=True, check=True).stdout.decode()
    names = [n for n in out.split("\0") if n]
    copied = 0
    for name in names:
        s = src / name
        if s.is_file() and not s.is_symlink():  # a tracked file deleted in the working tree is left out
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(s, dst / name)
            copied += 1
    # (with the digests numba_cache.follow keeps beside them: a mutated dependency drops them)
    for cache in [*src.glob("layerbvh/__pycache__/*.nb[ic]"), *src.glob("layerbvh/__pycache__/*.follows")]:
        (dst / cache.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(cache, dst / cache.relative_to(src))
    return copied


def import_path(copy: Path) -> Path:
    """A folder holding `layerbvh` and `layerbvh_mitsuba` (the copy's plugin/) as symlinks: the
    packages' names, pointing at the copied sources."""
    imp = copy / ".mutation_imports"
    imp.mkdir()
    (imp / "layerbvh").symlink_to(copy / "layerbvh", target_is_directory=True)
    (imp / "layerbvh_mitsuba").symlink_to(copy / "plugin", target_is_directory=True)
    return imp


def run_tests(python: str, copy: Path, env: dict, tests, timeout: float) -> tuple[int | None, str]:
    """pytest -x on `tests` in the copy: (exit status or None on timeout, output)."""
    cmd = [python, "-m", "pytest", "-x", "-v", "-n", "0", "-p", "no:cacheprovider", "-p", "no:randomly",
           "--no-header", "-rf", *tests]  # (-v: each test's id is printed as it starts; see crash_site)
    try:
        p = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        return None, (e.stdout or b"").decode(errors="replace") if isinstance(e.stdout, bytes) else (e.stdout or "")
    return p.returncode, p.stdout + p.stderr


def crash_site(rc: int | None, output: str, tests) -> str | None:
    """The listed test that was running when pytest was killed by a signal (a mutation that makes a
    kernel read out of bounds crashes the test that runs it: caught, as the suite's run fails
    there); None otherwise (a crash at import or elsewhere is not a catch)."""
    if rc is None or rc >= 0:
        return None
    # pytest -v prints a test's id when it starts and its result when it ends: the last id printed
    # without a result is the test that was running.
    started = re.findall(r"^(\S+::\S+) (?!PASSED|FAILED|SKIPPED|ERROR|XFAIL|XPASS)", output, re.M)
    running = started[-1] if started else None
    if running is None:
        return None
    # (A listed test without parameters names all its parametrized cases.)
    return next((t for t in tests if running.endswith(t) or running.split("[")[0].endswith(t)), None)


def first_failure(output: str, width: int = 90) -> str:
    """The first failed test of pytest's -rf summary, with the start of its message."""
    m = re.search(r"^FAILED (\S+)(?: - (.*))?$", output, re.M)
    if not m:
        return "?"
    why = (m.group(2) or "").strip()
    return m.group(1) + (f": {why[:width]}{'...' if len(why) > width else ''}" if why else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1], help="the checkout to copy")
    ap.add_argument("--python", default=None, help="the interpreter (default: REPO/.venv/bin/python)")
    ap.add_argument("--only", default="", help="comma-separated mutation names")
    ap.add_argument("--list", action="store_true", help="print the mutations and exit")
    ap.add_argument("--dry-run", action="store_true",
                    help="only check that each mutation's text occurs exactly once in the checkout and its tests' "
                    "files exist (no copy, no tests)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run of the listed tests")
    ap.add_argument("--keep", action="store_true", help="keep the temporary copy")
    ap.add_argument("--timeout", type=float, default=600, help="seconds per pytest run")
    args = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only.split(",")]
    unknown = set(filter(None, args.only.split(","))) - {m.name for m in MUTATIONS}
    if unknown:
        print(f"mutation_check: unknown mutation(s): {', '.join(sorted(unknown))}", file=sys.stderr)
        return 2
    if args.list:
        for m in chosen:
            print(f"{m.name}: {m.what}\n    {m.path}: {m.old.strip()!r} -> {m.new.strip()!r}\n    tests: "
                  + " ".join(m.tests))
        return 0
    repo = args.repo.resolve()
    if args.dry_run:
        bad = 0
        for m in chosen:
            there = (repo / m.path).is_file()
            found = (repo / m.path).read_text().count(m.old) if there else 0
            missing = [t for t in m.tests if not (repo / t.split("::")[0]).is_file()]
            bad += found != 1 or bool(missing)
            why = [] if found == 1 else [f"its text occurs {found} times in {m.path}" if there else f"no file {m.path}"]
            why += [f"no test file {t.split('::')[0]}" for t in missing]
            print(f"{m.name:34s} {'not applicable: ' + '; '.join(why) if why else 'applicable'}")
        return 1 if bad else 0
    python = args.python or str(repo / ".venv" / "bin" / "python")
    t_start = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="layerbvh-mutation-"))
    try:
        copy = tmp / "repo"
        n = copy_repository(repo, copy)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(import_path(copy)),
                                                                          os.environ.get("PYTHONPATH")])),
               "PYTHONDONTWRITEBYTECODE": "1", "COLUMNS": "250",  # COLUMNS: pytest's summary lines whole
               "LAYERBVH_VALGRIND_TEST": "1"}  # (the valgrind test, off in the suite's time budget)
        probe = subprocess.run([python, "-c", "import layerbvh, layerbvh_mitsuba, os; "
                                "print(os.path.realpath(layerbvh.__file__)); "
                                "print(os.path.realpath(layerbvh_mitsuba.__file__))"],
                               cwd=copy, env=env, capture_output=True, text=True)
        where = probe.stdout.split()
        if probe.returncode != 0 or len(where) != 2 or not all(w.startswith(str(copy.resolve())) for w in where):
            print(f"mutation_check: the copy does not import its own packages: {where or probe.stderr.strip()}",
                  file=sys.stderr)
            return 2
        print(f"mutation_check: {n} files copied to {copy}; {len(chosen)} mutation(s)", flush=True)
        if not args.no_baseline:
            tests = list(dict.fromkeys(t for m in chosen for t in m.tests))
            rc, out = run_tests(python, copy, env, tests, args.timeout * 2)
            if rc != 0:
                print(f"mutation_check: the unmutated copy fails its tests (exit {rc}): {first_failure(out)}\n"
                      + out[-3000:], file=sys.stderr)
                return 2
            print(f"baseline: {len(tests)} tests pass unmutated", flush=True)
        bad = skipped = 0
        flags = memmodel.cpu_flags()
        for m in chosen:
            if m.cpu_flag and m.cpu_flag not in flags:  # (an AVX2 CPU's ISA override changes nothing to catch)
                print(f"{m.name:34s} skipped: this CPU has no {m.cpu_flag}, which the bug needs to show", flush=True)
                skipped += 1
                continue
            target = copy / m.path
            text = target.read_text()
            found = text.count(m.old)
            if found != 1:
                print(f"{m.name:34s} not applicable: its text occurs {found} times in {m.path} (update the table)",
                      flush=True)
                bad += 1
                continue
            t0 = time.perf_counter()
            target.write_text(text.replace(m.old, m.new))
            try:
                rc, out = run_tests(python, copy, env, m.tests, args.timeout)
            finally:
                target.write_text(text)
            dt = time.perf_counter() - t0
            crashed_in = crash_site(rc, out, m.tests)
            if rc == 1:
                print(f"{m.name:34s} caught   by {first_failure(out)} ({dt:.0f} s)", flush=True)
            elif crashed_in:
                print(f"{m.name:34s} caught   by {crashed_in}: the test's process crashed (signal {-rc}; the suite "
                      f"stops there, naming it) ({dt:.0f} s)", flush=True)
            else:
                bad += 1
                why = "MISSED" if rc == 0 else ("ERROR    (timeout)" if rc is None else f"ERROR    (pytest exit {rc})")
                print(f"{m.name:34s} {why}: {m.what} ({dt:.0f} s)", flush=True)
                if rc not in (0, None):
                    print(out[-2000:], flush=True)
        print(f"mutation_check: {len(chosen) - bad - skipped} of {len(chosen) - skipped} caught"
              + (f" ({skipped} skipped on this CPU)" if skipped else "") + f" in {time.perf_counter() - t_start:.0f} s",
              flush=True)
        return 1 if bad else 0
    finally:
        if args.keep:
            print(f"mutation_check: copy kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
