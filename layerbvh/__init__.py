"""layerbvh: Layer BVH build, layout and exact sorted wavefront traversal on Dr.Jit."""
from .auto import AUTO, AutoPolicy, choice_key
from .backend import (LLVM_ISAS, apply_llvm_isa_from_env, cpu_model, from_numpy, llvm_isa, llvm_vector_width,
                      set_llvm_isa, set_llvm_vector_width)
from .inputs import (DEFAULT_BRANCHING, DEFAULT_LEAF_SIZE, default_leaf_size, DEFAULT_TREELET_HEIGHT, PARAM_RANGES,
                     check_mesh, check_param)
from .collector import collector_held
from .bvh import BATCH_RAYS, TRACE_MODES, Hits, LayerBVH, Occlusion, build, build_instanced
from .instances import Group, Instance
from .layout import BRANCHINGS, LayerLayout, check_layout
from .locality import (LocalityRow, LocalitySettings, RaySet, check_trace, limits as step_limits, measure, replay,
                       replay_tree, row as locality_row, sample_rays)
from .locality_verdict import at_headline, headline_config, preset_verdict
from .memmodel import PRESETS, CacheLevel, Preset, preset
from . import meshes  # noqa: F401  (the engine's test and benchmark inputs, numpy only)
from .sah import MAX_DEPTH
from .state import MISS
from .stats import BVHStats, TraceStats
from .wavefront import MODES, TAIL_STEPS

__all__ = ["AUTO", "AutoPolicy", "choice_key", "BATCH_RAYS", "TRACE_MODES", "build", "build_instanced", "Group",
           "Instance", "LayerBVH", "Hits", "Occlusion", "BVHStats", "TraceStats",
           "LayerLayout", "check_layout", "MODES", "TAIL_STEPS", "MISS", "PARAM_RANGES", "check_mesh", "check_param",
           "DEFAULT_TREELET_HEIGHT", "DEFAULT_LEAF_SIZE", "DEFAULT_BRANCHING", "BRANCHINGS", "default_leaf_size",
           "MAX_DEPTH", "cpu_model", "from_numpy", "llvm_vector_width", "set_llvm_vector_width", "LLVM_ISAS",
           "llvm_isa",
           "set_llvm_isa", "collector_held",
           # the locality model
           "LocalityRow", "LocalitySettings", "RaySet", "at_headline", "headline_config", "measure", "preset_verdict",
           "replay", "replay_tree", "check_trace", "locality_row", "step_limits", "sample_rays",
           "PRESETS", "CacheLevel", "Preset", "preset"]
__version__ = "0.1.0"

apply_llvm_isa_from_env()  # LAYERBVH_LLVM_ISA: before any kernel is compiled
from .kernel_census import start_from_env as _census
_census()  # LAYERBVH_KERNEL_CENSUS: off unless set (scripts/kernel_census.py)
