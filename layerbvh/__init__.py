"""layerbvh: Layer BVH build, layout and exact sorted wavefront traversal on Dr.Jit."""
from .bvh import AUTO, MISS, TRACE_MODES, BVHStats, Hits, LayerBVH, build
from .layout import LayerLayout, check_layout
from .stats import TraceStats
from .wavefront import MODES

__all__ = ["AUTO", "TRACE_MODES", "build", "LayerBVH", "Hits", "BVHStats", "TraceStats", "LayerLayout", "check_layout", "MODES", "MISS"]
__version__ = "0.1.0"
