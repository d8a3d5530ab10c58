"""The locality replay's vocabulary: its load sites (one load instruction each), the columns of a ray's replay state,
and the layout's records as the replay reads them."""
from __future__ import annotations

import numpy as np

from .geometry import EDGE_ERR, FAR_SCALE, FAR_UNIT, MIN_RCP_INPUT
from .layout import (BRANCHINGS, EXIT_BIT, LEAF_BIT, LEAF_COUNT_SHIFT, LEAF_FIRST_MASK, NODE_BOX_HI, NODE_BOX_LO,
                     FAR_COORD, NODE_LINK, PAYLOAD_MASK, POP, TRI_FLOATS, TRI_NORMAL, TRI_VERTEX, LayerLayout,
                     node_format)

# -- constants as plain ints/float32 (numba folds them; numpy uint32 would promote to float) ------
_LEAF, _EXIT, _PAYLOAD = int(LEAF_BIT), int(EXIT_BIT), int(PAYLOAD_MASK)
_FIRST, _SHIFT, _POP = int(LEAF_FIRST_MASK), LEAF_COUNT_SHIFT, int(POP)
_FAR = np.float32(FAR_SCALE)            # Dr.Jit multiplies a Float by a Python float in float32
_EDGE = np.float32(EDGE_ERR)
_FAR_COORD, _FAR_UNIT = np.float32(FAR_COORD), np.float32(FAR_UNIT)
_MIN_RCP = np.float32(MIN_RCP_INPUT)
_LO0, _LO1, _HI0, _HI1 = NODE_BOX_LO[0], NODE_BOX_LO[1], NODE_BOX_HI[0], NODE_BOX_HI[1]
_LK0, _LK1 = NODE_LINK
_V0, _V1, _V2 = TRI_VERTEX
_NRM = TRI_NORMAL // 2                  # first float64 slot of the stored normal
_FLT_MAX = np.float32(3.4028234663852886e38)  # walk's clamp of a hit child's entry distance

# -- per-ray state: columns of the float32 and int64 state tables -----------------------------------
F_O, F_D, F_INV, F_SX, F_SY, F_SZ, F_T, F_U, F_V = 0, 3, 6, 9, 10, 11, 12, 13, 14
F_COLS = 16
(I_KX, I_KY, I_KZ, I_PRIM, I_LINK, I_SP, I_TRELET, I_DONE, I_INNER, I_LEAF, I_TRI, I_ITER, I_STEPS,
 I_SPILL, I_HITW, I_TRI_CUR, I_TRI_END, I_NL, I_ACTIVE, I_NEXT, I_HITS) = range(21)
I_COLS = 21

# -- load sites (one load instruction each) ----------------------------------------------------------
(S_TRI, S_LOC_R_LINK, S_LOC_R_T, S_STACK_LINK, S_STACK_T, S_NODE_TRELET, S_TF, S_NODE, S_LOC_W_LINK,
 S_LOC_W_T) = range(10)
# A wide node's push j (j = 0 on top) writes two local slot sites: j = 0 the two above (the binary
# push's), j >= 1 a pair from S_PUSH on (link, then entry distance).
MAX_PUSH = max(BRANCHINGS) - 1
S_PUSH = 10
S_START = S_PUSH + 2 * (MAX_PUSH - 1)  # first of the per-kernel ray/state loads (StartLoads)
S_END = S_START + 10
# The kernels' stores as a lane ends (issue 57, item 5): its hit to the results (t, prim, u, v by
# slot: per_ray's every ray, a step's or the tail's closer hits), and in a wavefront step its sort
# key and, for a ray that goes on, its state record (both in lane order) and the entries it still
# holds (above its global stack: walk's spill); in the first step also, by slot, the ray record of
# a ray that goes on (state.RayRecords.write).
(S_RES_T, S_RES_PRIM, S_RES_U, S_RES_V, S_KEY_OUT, S_STATE_OUT, S_SPILL_LINK, S_SPILL_T,
 S_RAY_OUT) = range(S_END, S_END + 9)
# The trace call's own passes before its first kernel (memstores.setup_passes): what they read and
# what they write.
S_SETUP_LOAD, S_SETUP_STORE = S_END + 9, S_END + 10
# A CPU kernel's stack frame (the registers LLVM spills, beside the local arrays the local sites
# model): `site_bytes[S_FRAME_READ]` bytes per packet slot, read and written once a packet
# iteration (0: none, as on a GPU, where they stay in registers).
S_FRAME_READ, S_FRAME_WRITE = S_END + 11, S_END + 12
SITES = S_END + 13
# A launch, as memtrace.run_kernel's `bounded` takes it: a walk to the end (per_ray, the tail), a
# wavefront step, or the first step (which also writes the ray records).
WHOLE, STEP, FIRST_STEP = 0, 1, 2
SITE_NAMES = ("triangle", "local_read_link", "local_read_t", "stack_link", "stack_t", "node_treelet",
              "treelet_root", "node", "local_write_link", "local_write_t") + tuple(
                  f"local_write_{w}_{j}" for j in range(1, MAX_PUSH) for w in ("link", "t"))
# What each site is, for the per-kind breakdown of transactions and traffic.
CATEGORY = {"node": (S_NODE, S_NODE_TRELET, S_TF), "triangle": (S_TRI,), "stack": (S_STACK_LINK, S_STACK_T),
            "local": (S_LOC_R_LINK, S_LOC_R_T, S_LOC_W_LINK, S_LOC_W_T) + tuple(range(S_PUSH, S_START)),
            "results": (S_RES_T, S_RES_PRIM, S_RES_U, S_RES_V),
            "step out": (S_KEY_OUT, S_STATE_OUT, S_SPILL_LINK, S_SPILL_T, S_RAY_OUT),
            "set-up": (S_SETUP_LOAD, S_SETUP_STORE), "frame": (S_FRAME_READ, S_FRAME_WRITE)}
# ... and the start sites are "ray". The local write sites and the sites from S_END on are the
# replay's stores (the cache model's write-allocate and write-back, cachesim.py); every other site
# loads. The sites before S_END are the traversal's own traffic (its transactions and DRAM bytes);
# from S_END on, what the kernels write out, which the between-step bytes (steptraffic) count.
STORE_SITES = (S_LOC_W_LINK, S_LOC_W_T) + tuple(range(S_PUSH, S_START)) + tuple(range(S_END, S_SETUP_LOAD)) + (
    S_SETUP_STORE, S_FRAME_WRITE)
# The kernel's loads by kind: the replay's load sites of each, and the work counter the kernel
# keeps of it (state.WORK); besides these, each kernel a ray takes part in ("steps") loads its ray
# (and in a wavefront step its state record) once.
LOAD_KINDS = {"node": ((S_NODE,), "inner_nodes"), "triangle": ((S_TRI,), "triangles"),
              "stack": ((S_STACK_LINK, S_STACK_T), "stack_reads"),
              "node_treelet": ((S_NODE_TRELET,), "treelet_reads"), "exit_root": ((S_TF,), "root_reads")}
NO_READ = -1


# Where a start load reads (StartLoads' `by`): the ray's own slot, its lane in this launch, its
# lane in the launch before (a state record gathered through the sort's permutation), or, in a
# wavefront step, the node its link names (a compact state record's treelet lookup: an exit
# link names its treelet and reads nothing); or nothing (a load this launch does not make: the
# first step knows its rays' treelet, the root's).
BY_SLOT, BY_LANE, BY_PREVIOUS_LANE, BY_LINK_NODE, BY_NONE = 0, 1, 2, 3, 4


def local_stack_rows(units: int, resident: int, warp: int) -> int:
    """Rows of the replay's local entry stacks: one per lane a unit can hold at once."""
    return units * resident * warp


def layout_views(lay: LayerLayout):
    """The layout's records as the replay reads them: node float32/uint32 rows, triangle
    float32/uint32/float64 rows, treelet roots, node treelets."""
    nodes = lay.nodes.reshape(-1, node_format(lay.branching).floats)
    tris = np.ascontiguousarray(lay.tris.reshape(-1, TRI_FLOATS))
    return (nodes, nodes.view(np.uint32), tris, tris.view(np.uint32), tris.view(np.float64),
            lay.treelet_first.astype(np.int64), lay.node_treelet.astype(np.int64))
