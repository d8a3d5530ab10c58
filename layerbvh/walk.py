"""The traversal kernel: a nearest-first stack walk over the Layer BVH, whole (per-ray) or one treelet at a time (wavefront step)."""
from __future__ import annotations

import drjit as dr

from .geometry import FAR_SCALE, Ray, hit_children, hit_triangle
from .layout import EXIT_BIT, LEAF_BIT, LEAF_COUNT, LEAF_FIRST, LEAF_UINTS, PAYLOAD_MASK, POP, DeviceLayout
from .state import RayState


def treelet_of(m, lay: DeviceLayout, link, active):
    """Treelet holding a node, leaf or exit link (exits name their treelet in the payload)."""
    payload = link & PAYLOAD_MASK
    is_leaf = (link & LEAF_BIT) != 0
    is_exit = ~is_leaf & ((link & EXIT_BIT) != 0)
    from_leaf = dr.gather(m.UInt32, lay.leaf_treelet, payload, active & is_leaf)
    from_node = dr.gather(m.UInt32, lay.node_treelet, payload, active & ~is_leaf & ~is_exit)
    return dr.select(is_leaf, from_leaf, dr.select(is_exit, payload, from_node))


@dr.syntax
def walk(m, lay: DeviceLayout, rays, s: RayState, stack, cap: int, bounded: bool, any_hit: bool,
         count_work: bool = True, active=None):
    """Advance every ray of `s`, nearest child first, until it finishes or (when `bounded`)
    is about to continue in another treelet than `s.treelet`. `rays` (state.SlotRays or
    state.RayRecords) gives each slot's origin and direction.

    With `count_work` False the work counters are left untouched (no statistics work).
    Entries pushed during this call live in a local stack of `cap` entries; entries pushed by
    earlier steps are read (never written) from the global `stack` = (links, t, capacity),
    so the kernel has no read-after-write on global memory. Rays where `active` (default: all)
    is False do not move. Returns the new state, whether each ray finished, the treelet it
    continues in, and its local entries for write-back.
    """
    ray = Ray(m, *rays.load(s.slot))
    # One spare slot: the unconditional write above the top must stay in bounds when full.
    loc_link = dr.alloc_local(m.UInt32, cap + 1, m.UInt32(0))
    loc_t = dr.alloc_local(m.Float, cap + 1, m.Float(0))
    nl = m.UInt32(0)
    link, sp = m.UInt32(s.link), m.UInt32(s.sp)
    t_best, u_best, v_best = m.Float(s.t), m.Float(s.u), m.Float(s.v)
    prim_best = m.UInt32(s.prim)
    zero = m.UInt32(0)
    n_inner, n_leaf, n_tri, n_iter = (m.UInt32(c) if count_work else zero
                                      for c in (s.n_inner, s.n_leaf, s.n_tri, s.n_iter))
    tri_cur, tri_end = m.UInt32(0), m.UInt32(0)
    done = m.Bool(False)
    next_treelet = m.UInt32(s.treelet)
    base = s.slot * stack[2] if stack is not None else m.UInt32(0)
    active = dr.full(m.Bool, True, dr.width(s.link)) if active is None else m.Bool(active)

    while active:
        if count_work:
            n_iter += 1
        # Exactly one of four things happens per iteration. Only the two heavy tests are real
        # branches; the stack is updated outside them with selects, which keeps every local
        # array access unconditional (Dr.Jit mis-counted pushes made inside nested branches).
        in_leaf = tri_cur < tri_end
        is_pop = ~in_leaf & (link == POP)
        is_leaf = ~in_leaf & ~is_pop & ((link & LEAF_BIT) != 0)
        is_node = ~in_leaf & ~is_pop & ~is_leaf

        if in_leaf:
            # Leaf work: one triangle per iteration, so rays in leaves and in nodes stay in step.
            hit, t, u, v, prim = hit_triangle(m, lay.tris, tri_cur, ray, active)
            closer = hit & ((t < t_best) | ((t == t_best) & (prim < prim_best)))
            t_best = dr.select(closer, t, t_best)
            u_best = dr.select(closer, u, u_best)
            v_best = dr.select(closer, v, v_best)
            prim_best = dr.select(closer, prim, prim_best)
            if any_hit:
                done |= closer
                active &= ~closer

        hit_l, hit_r = m.Bool(False), m.Bool(False)
        t_l, t_r = m.Float(0), m.Float(0)
        link_l, link_r = m.UInt32(POP), m.UInt32(POP)
        if is_node:
            payload = link & PAYLOAD_MASK
            is_exit = (link & EXIT_BIT) != 0
            node = dr.select(is_exit, dr.gather(m.UInt32, lay.treelet_first, payload, is_exit), payload)
            hit_l, hit_r, t_l, t_r, link_l, link_r = hit_children(m, lay.nodes, node, ray, t_best, is_node)

        # Leaf entry: read the triangle range.
        leaf = link & PAYLOAD_MASK
        first = dr.gather(m.UInt32, lay.leaves, LEAF_UINTS * leaf + LEAF_FIRST, is_leaf)
        count = dr.gather(m.UInt32, lay.leaves, LEAF_UINTS * leaf + LEAF_COUNT, is_leaf)
        tri_cur = dr.select(is_leaf, first, dr.select(in_leaf, tri_cur + 1, tri_cur))
        tri_end = dr.select(is_leaf, first + count, tri_end)

        # Pop: local entries (pushed in this call) first, then the global stack.
        from_local = is_pop & (nl > 0)
        from_global = is_pop & ~from_local & (sp > 0) if stack is not None else m.Bool(False)
        nl = dr.select(from_local, nl - 1, nl)
        sp = dr.select(from_global, sp - 1, sp)
        e_link = m.UInt32(loc_link[nl])
        e_t = m.Float(loc_t[nl])
        if stack is not None:
            e_link = dr.select(from_global, dr.gather(m.UInt32, stack[0], base + sp, from_global), e_link)
            e_t = dr.select(from_global, dr.gather(m.Float, stack[1], base + sp, from_global), e_t)
        empty = is_pop & ~from_local & ~from_global
        # An entry farther than the closest hit found since it was pushed is culled (with the slab
        # test's rounding margin, as in hit_children: ties must stay reachable).
        popped = dr.select((from_local | from_global) & (e_t <= t_best * FAR_SCALE), e_link, POP)

        # Node: continue with the nearer child, push the farther one when both are hit.
        right_first = hit_r & (~hit_l | (t_r < t_l))
        near = dr.select(right_first, link_r, link_l)
        push = hit_l & hit_r
        loc_link[nl] = dr.select(right_first, link_l, link_r)  # above the top: harmless if not pushed
        loc_t[nl] = dr.select(right_first, t_l, t_r)
        nl = dr.select(push, nl + 1, nl)
        descend = dr.select(hit_l | hit_r, near, POP)

        link = dr.select(is_pop, popped, dr.select(is_leaf, POP, dr.select(is_node, descend, link)))
        if count_work:  # statistics cost registers and adds; only when asked for
            n_inner = dr.select(is_node, n_inner + 1, n_inner)
            n_leaf = dr.select(is_leaf, n_leaf + 1, n_leaf)
            n_tri = dr.select(in_leaf, n_tri + 1, n_tri)
        done |= empty
        active &= ~empty
        if bounded:
            # A popped entry of another treelet, or an exit taken as the nearer child, ends the step.
            tre = treelet_of(m, lay, popped, is_pop & (popped != POP))
            leave_pop = is_pop & (popped != POP) & (tre != s.treelet)
            leave_exit = is_node & (hit_l | hit_r) & ((near & LEAF_BIT) == 0) & ((near & EXIT_BIT) != 0)
            next_treelet = dr.select(leave_pop, tre, dr.select(leave_exit, near & PAYLOAD_MASK, next_treelet))
            active &= ~(leave_pop | leave_exit)

    out = RayState(t=t_best, u=u_best, v=v_best, prim=prim_best, link=link, sp=sp, slot=s.slot,
                   treelet=next_treelet)
    if count_work:
        out.n_inner, out.n_leaf, out.n_tri, out.n_iter = n_inner, n_leaf, n_tri, n_iter
    local = [(m.UInt32(loc_link[k]), m.Float(loc_t[k])) for k in range(cap)]
    return out, done, nl, local
