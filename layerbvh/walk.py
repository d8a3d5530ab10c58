"""The traversal kernel: a nearest-first stack walk over the Layer BVH, whole (per-ray) or one treelet at a time
(wavefront step)."""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .geometry import FAR_SCALE, hit_children, hit_children_wide, hit_triangle, setup_ray, to_object_space
from .layout import (EXIT_BIT, INSTANCE_TAG, LEAF_BIT, LEAF_FIRST_MASK, LEAVE, PAYLOAD_MASK, POP, DeviceLayout,
                     leaf_range, node_format)
from .loopstate import Held
from .state import MISS, EntryStack, RayState

# Sorting networks that order a wide node's children by entry distance (compare-exchange pairs,
# Knuth, TAOCP vol. 3, 5.3.4: 5 comparators for 4 inputs, 19 for 8, both optimal).
SORT_NETWORKS = {
    4: ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)),
    8: ((0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7), (0, 1), (2, 3), (4, 5), (6, 7),
        (2, 4), (3, 5), (1, 4), (3, 6), (1, 2), (3, 4), (5, 6)),
}
# Entry distances of hit children are clamped below this before sorting, so a hit always sorts
# before a miss (whose key is inf) even if its distance overflowed to inf.
_FLT_MAX = 3.4028234663852886e38


def walk(m, lay: DeviceLayout, rays, s: RayState, *, stack: EntryStack | None, cap: int, bounded: bool,
         any_hit: bool, count_work: bool = True, active=None, results=None, spill: EntryStack | None = None):
    """Advance every ray of `s`, nearest child first, until it finishes or (when `bounded`)
    is about to continue in another treelet than the step's (`s.treelet`; None: a compact state
    record's, found from its link). `rays` (state.SlotRays,
    state.RayRecords or state.DirectRays) gives each slot's origin and direction.

    One loop iteration does, in this order, whatever of these a ray needs: test one triangle of the
    leaf it is in; take the next entry from its stack (culled when farther than the closest hit so
    far); test both children of the node it is at, going on with the nearer and pushing the farther
    (a wide node: all its children, on with the nearest, the other hit ones pushed far to near, so
    the nearest of them is popped first); enter the leaf it reached (a leaf link carries its
    triangle range, so the next iteration tests the first triangle). So a node whose children both
    miss costs no extra iteration to pop, and no iteration reads a leaf record. Stack memory is
    touched only on a push or a pop.

    With `count_work` False the work counters are left untouched (no statistics work).
    Entries pushed during this call live in a local stack of `cap` entries; entries pushed by
    earlier steps are read from the global `stack` (state.EntryStack; None: none), never through
    it: only through `spill` (below), after the ray's last read of it. Rays where `active`
    (default: all) is False do not move. Returns the new state (its `treelet`: where the ray
    continues) and whether each ray finished.

    In a wavefront step (the layer modes, issue 40) the kernel keeps its own books, so that
    between steps a ray moves only its state record (state.StateRecords): with `results` given, a ray
    writes each closer hit's t, u, v and prim there by slot as it finds it (so `s` need not carry
    u and v); with `spill` (the global stack's write alias, wavefront.trace), a ray that goes on
    writes the entries it still holds above its global stack when its walk ends, so an entry
    consumed within the step never leaves the kernel's local stack, and no kernel moves entries
    between steps; the state's sp then counts the entries held.

    In a bounded step, an entry's treelet is known without a lookup where it matters: entries
    pushed in this step belong to the step's treelet unless they are exits (which name theirs);
    a popped global entry of another treelet ends the step, except a leaf, which is simply
    tested here (leaf work reads triangles, not the treelet's nodes).

    Instanced layouts (lay.instances set; the code below is compiled only for them): reaching
    an instance link (a top-level leaf), a ray pushes the LEAVE marker (entry distance 0, never
    culled), maps itself into the instance's object space and goes on at the root of its group;
    every entry pushed from there lies above the marker, so popping the marker (back to world
    space) happens exactly when the instance is done. Entering an instance ends a bounded step:
    the group's root treelet is always another treelet (its key for the sort). Hits are ordered
    by (t, instance, primitive): ties in t go to the lower instance index, then the lower
    primitive id, in every mode.
    """
    out, done, nl, u_best, v_best = _walk(m, lay, rays, s, stack, cap, bounded, any_hit, count_work, active,
                                          results, spill)
    if results is None:
        out.u, out.v = u_best, v_best
    if spill is not None:  # (sp then counts the entries the ray holds: the kernel wrote them above it)
        nl = dr.select(done, 0, nl)
        out.sp = out.sp + nl
    return out, done


@dr.syntax
def _walk(m, lay: DeviceLayout, rays, s: RayState, stack: EntryStack | None, cap: int, bounded: bool, any_hit: bool,
          count_work: bool, active, results, spill: EntryStack | None):
    """`walk`'s loop (Dr.Jit's @syntax rewrite takes positional parameters only); returns the
    state without u and v, done, the local entry count, and u, v apart. The hits (`results`) are
    written as they happen, and the held entries (`spill`) on the iteration a ray's walk ends,
    both inside the loop."""
    world_o, world_d = rays.load(s.slot)
    instanced = lay.instances is not None
    wide = lay.branching > 2  # (a plain int and bool: the loop's state takes no dataclass)
    n_slots = lay.branching - 1  # entries a wide node can push
    ray = _start_ray(m, lay, s, world_o, world_d)
    # Without instances both stay MISS (unused, but every name the loop touches must exist).
    in_inst = m.UInt32(s.inst) if instanced else m.UInt32(MISS)
    hit_inst = m.UInt32(s.hit_inst) if instanced else m.UInt32(MISS)
    # Uninitialized: a slot is read only below `nl` (what this walk pushed) or, as a pop's select
    # that other lanes discard, at nl itself. Filled with zeros, each packet first wrote its whole
    # local stack (an LLVM memset per packet: 4 KiB for 8 lanes of 65 slots), which the locality
    # model never had (PERFORMANCE.md entry 69).
    loc_link = dr.alloc_local(m.UInt32, cap + 1)
    loc_t = dr.alloc_local(m.Float, cap + 1)
    nl = m.UInt32(0)
    link, sp = m.UInt32(s.link), m.UInt32(s.sp)
    t_best = m.Float(s.t)
    n_lanes = dr.width(s.link)
    u_best, v_best = (m.Float(s.u), m.Float(s.v)) if s.u is not None else \
        (dr.zeros(m.Float, n_lanes), dr.zeros(m.Float, n_lanes))
    prim_best = m.UInt32(s.prim)
    zero = m.UInt32(0)
    n_inner, n_leaf, n_tri, n_iter = (m.UInt32(c) if count_work else zero
                                      for c in (s.n_inner, s.n_leaf, s.n_tri, s.n_iter))
    n_steps = m.UInt32(s.n_steps) + 1 if count_work else zero
    n_top, n_enter = (m.UInt32(s.n_top), m.UInt32(s.n_enter)) if count_work and instanced else (zero, zero)
    # Loads per kind besides node records and triangles (n_inner, n_tri): global entry-stack
    # entries, node-treelet lookups, exit roots; locality.check_trace holds them against the replay.
    n_stack, n_treelet, n_root = (m.UInt32(c) if count_work else zero for c in (s.n_stack, s.n_treelet, s.n_root))
    # ... and the stores a wavefront step makes as it goes (state.WORK): entries spilled, hits written.
    n_spill, n_hitw = (m.UInt32(c) if count_work else zero for c in (s.n_spill, s.n_hitw))
    tri_cur, tri_end = m.UInt32(0), m.UInt32(0)
    done = m.Bool(False)
    step_treelet = s.treelet
    if dr.hint(step_treelet is None, mode="scalar"):  # a compact state record: no treelet stored
        step_treelet, n_treelet = _record_treelet(m, lay, s.link, n_treelet, count_work, bounded)
    next_treelet = m.UInt32(step_treelet)
    # (opaque: one kernel per tree depth)
    base = s.slot * dr.opaque(m.UInt32, stack.rows) if stack is not None else m.UInt32(0)
    active = dr.full(m.Bool, True, dr.width(s.link)) if active is None else m.Bool(active)
    # The loop's state is what its body changes. @syntax makes every name the body reads or
    # writes a state variable, and Dr.Jit, finding one unchanged after tracing the body, traces
    # the whole body a second time without it: twice the host time of every walk (PERFORMANCE.md
    # entry 58). So what the body only reads, and what this walk's configuration never changes
    # (the ray outside instances, counters it does not keep, the stack pointer without a global
    # stack, the next treelet of an unbounded walk), enter it Held: opaque to Dr.Jit, read as before.
    lay, s, stack, spill, results = (Held.of(x) for x in (lay, s, stack, spill, results))
    fixed = Held(_Fixed(base=base, step_treelet=step_treelet, world_o=world_o, world_d=world_d))
    counting = dict(inner=count_work, instanced=count_work and instanced, stack=count_work and stack is not None,
                    treelet=count_work and bounded, spill=count_work and spill is not None,
                    hitw=count_work and results is not None)
    ray, in_inst, hit_inst = (Held.unless(instanced, x) for x in (ray, in_inst, hit_inst))
    n_inner, n_leaf, n_tri, n_iter, n_root = (Held.unless(counting["inner"], x)
                                              for x in (n_inner, n_leaf, n_tri, n_iter, n_root))
    n_top, n_enter = (Held.unless(counting["instanced"], x) for x in (n_top, n_enter))
    n_stack = Held.unless(counting["stack"], n_stack)
    n_treelet = Held.unless(counting["treelet"], n_treelet)
    n_spill = Held.unless(counting["spill"], n_spill)
    n_hitw = Held.unless(counting["hitw"], n_hitw)
    sp = Held.unless(stack is not None, sp)
    next_treelet = Held.unless(bounded, next_treelet)

    while active:
        if count_work:
            n_iter += 1
        if dr.hint(spill is not None, mode="scalar"):  # (plain Python: per_ray's kernel is left as it was)
            walking = m.Bool(active)  # the rays whose walk may end in this iteration

        # -- a triangle of the current leaf --
        if tri_cur < tri_end:
            closer, t_best, u_best, v_best, prim_best, hit_inst = _test_triangle(
                m, lay, ray, tri_cur, active, t_best, u_best, v_best, prim_best, in_inst, hit_inst, instanced,
                results, s.slot)
            if count_work and results is not None:
                n_hitw += dr.select(closer, m.UInt32(1), m.UInt32(0))
            tri_cur += 1
            if count_work:
                n_tri += 1
            if any_hit:
                done |= closer
                active &= ~closer

        # -- the next entry, when the leaf is done and no node is at hand --
        # (Local array accesses stay outside branches: inside one they ran for lanes that did
        # not take it and went wrong; so pops and pushes are selects, and a lane that does not
        # push writes the spare slot `cap`.)
        want = active & (tri_cur >= tri_end) & (link == POP)
        from_local = want & (nl > 0)
        nl = dr.select(from_local, nl - 1, nl)
        e_link, e_t = m.UInt32(loc_link[nl]), m.Float(loc_t[nl])
        from_global = m.Bool(False)
        if stack is not None:
            from_global, sp, e_link, e_t, n_stack = _pop_global(m, stack, fixed.base, want & ~from_local, sp, e_link,
                                                                 e_t, n_stack, count_work)
        empty = want & ~from_local & ~from_global
        done |= empty
        active &= ~empty
        # An entry farther than the closest hit found since it was pushed is culled (with the
        # slab test's rounding margin, as in hit_children: ties must stay reachable).
        link = dr.select(want, dr.select(active & (e_t <= t_best * FAR_SCALE), e_link, POP), link)
        if instanced:
            link, in_inst, ray = _leave_instance(m, want, link, in_inst, ray, fixed.world_o, fixed.world_d)
        if bounded:
            leave, tre, n_treelet = _entry_treelet(m, lay, fixed.step_treelet, want, active, link, from_global,
                                                   n_treelet, count_work)
            next_treelet = dr.select(leave, tre, next_treelet)
            active &= ~leave

        # -- an instance: into its object space, the LEAVE marker pushed below its entries --
        entered = m.Bool(False)
        if instanced:
            entered, in_inst, ray, link, n_enter, next_treelet, active = _enter_instance(
                m, lay, active, tri_cur, tri_end, link, in_inst, ray, fixed.world_o, fixed.world_d, n_enter,
                next_treelet, count_work, bounded)

        # -- a node: all children; on with the nearest, push the others (far to near) --
        # Binary: `push` says whether the farther child is pushed. Wide: `n_push` entries,
        # push_links/push_ts[j] going to stack position nl + n_push - 1 - j (j = 0 on top).
        push = m.Bool(False)
        far_link, far_t = m.UInt32(0), m.Float(0)
        n_push = m.UInt32(0)
        push_links = tuple(m.UInt32(0) for _ in range(n_slots)) if wide else ()
        push_ts = tuple(m.Float(0) for _ in range(n_slots)) if wide else ()
        at_node = active & (tri_cur >= tri_end) & (link != POP) & ((link & LEAF_BIT) == 0)
        if instanced:  # the marker is this iteration's push
            push = m.Bool(entered)
            far_link = dr.select(entered, m.UInt32(LEAVE), far_link)
            if wide:
                n_push = dr.select(entered, m.UInt32(1), n_push)
                push_links = (far_link,) + push_links[1:]
            at_node &= ~entered
        if at_node:
            payload = link & PAYLOAD_MASK
            is_exit = (link & EXIT_BIT) != 0
            node = m.UInt32(payload)
            if is_exit:  # only the first node of a step (or of the per-ray tail) enters this way
                node = dr.gather(m.UInt32, lay.treelet_first, payload)
                if count_work:
                    n_root += 1
            if count_work:
                n_inner += 1
                if instanced:
                    n_top += dr.select(in_inst == MISS, m.UInt32(1), m.UInt32(0))
            if wide:
                link, n_push, push_links, push_ts = _wide_node(m, lay, node, ray, t_best, active)
            else:
                hit_l, hit_r, t_l, t_r, link_l, link_r = hit_children(m, lay.nodes, node, ray, t_best, active)
                right_first = hit_r & (~hit_l | (t_r < t_l))
                push = hit_l & hit_r
                far_link = dr.select(right_first, link_l, link_r)
                far_t = dr.select(right_first, t_l, t_r)
                link = dr.select(hit_l | hit_r, dr.select(right_first, link_r, link_l), POP)
            if bounded:
                if (link != POP) & ((link & LEAF_BIT) == 0) & ((link & EXIT_BIT) != 0):
                    # The nearer child is in another treelet: this step ends here.
                    next_treelet = link & PAYLOAD_MASK
                    active &= False
        if wide:
            nl = _push_wide(m, loc_link, loc_t, nl, n_push, push_links, push_ts, cap)
        else:
            nl = _push_binary(m, loc_link, loc_t, nl, push, far_link, far_t, cap)

        # -- a leaf: its triangles from the next iteration on (an instance link waits for the
        # next iteration, which enters it) --
        at_leaf = active & (link != POP) & ((link & LEAF_BIT) != 0)
        if instanced:
            at_leaf &= link < INSTANCE_TAG
        if at_leaf:
            first, count = leaf_range(link)
            tri_cur, tri_end = m.UInt32(first), first + count
            link = m.UInt32(POP)
            if count_work:
                n_leaf += 1

        if dr.hint(spill is not None, mode="scalar"):  # -- a step's end: the entries the ray holds, written back --
            n_spill = _spill_held(m, spill, loc_link, loc_t, cap, walking & ~active & ~done, fixed.base + sp, nl,
                                  n_spill, count_work)

    ray, in_inst, hit_inst, sp, next_treelet = (Held.value(x) for x in (ray, in_inst, hit_inst, sp, next_treelet))
    n_inner, n_leaf, n_tri, n_iter, n_root, n_top, n_enter, n_stack, n_treelet, n_spill, n_hitw = (
        Held.value(x) for x in (n_inner, n_leaf, n_tri, n_iter, n_root, n_top, n_enter, n_stack, n_treelet, n_spill,
                                 n_hitw))
    out = RayState(t=t_best, prim=prim_best, link=link, sp=sp, slot=s.slot, treelet=next_treelet)
    if instanced:
        out.inst, out.hit_inst = in_inst, hit_inst
    if count_work:
        out.n_inner, out.n_leaf, out.n_tri, out.n_iter, out.n_steps = n_inner, n_leaf, n_tri, n_iter, n_steps
        out.n_stack, out.n_treelet, out.n_root = n_stack, n_treelet, n_root
        out.n_spill, out.n_hitw = n_spill, n_hitw
        if instanced:
            out.n_top, out.n_enter = n_top, n_enter
    return out, done, nl, u_best, v_best


@dataclass(frozen=True)
class _Fixed:
    """What a walk's loop reads and never changes besides the tree and the state: the ray's
    global stack base, the step's treelet, the ray in world space."""

    base: object
    step_treelet: object
    world_o: object
    world_d: object


@dr.syntax
def _spill_held(m, spill: EntryStack, loc_link, loc_t, cap: int, ending, top, nl, n_spill, count_work: bool):
    """A wavefront step's write-back, on the iteration where a ray's walk ends and it goes on
    (`ending`): its first `nl` local entries go to rows `top`.. of its global stack. The kernel
    reads that stack too (its pops), through the stack itself; `spill` maps the same memory
    (wavefront.trace), so Dr.Jit does not copy the stack whole before writing (copy-on-write).
    That is safe because a ray's reads all come before its writes (they feed the walk whose end
    gives `top` and the entries), and no other ray touches its rows. (Entry 33 of PERFORMANCE.md:
    written as each push happened, an alias gave wrong hits, a pop re-reading a slot the kernel
    had pushed, the two arrays being `noalias` to LLVM; written after the loop, each local slot
    read there made Dr.Jit run the whole loop again in a kernel of its own.) Returns n_spill with
    the stores counted (statistics runs)."""
    if ending:  # (a branch: a packet where no ray's walk ends skips the stores)
        for k in range(cap):
            keep = ending & (m.UInt32(k) < nl)
            dr.scatter(spill.link, m.UInt32(loc_link[k]), top + k, keep)
            dr.scatter(spill.t, m.Float(loc_t[k]), top + k, keep)
            if count_work:
                n_spill += dr.select(keep, m.UInt32(1), m.UInt32(0))
    return n_spill


@dr.syntax
def _test_triangle(m, lay: DeviceLayout, ray, tri, active, t_best, u_best, v_best, prim_best, in_inst, hit_inst,
                   instanced: bool, results, slot):
    """One triangle of the current leaf against the closest hit so far: (closer, and the closest
    hit's t, u, v, prim and instance). Ties in t go by (instance, primitive). In a wavefront step
    (`results` given) a closer hit is written by slot at once (see walk's docstring)."""
    hit, t, u, v, prim = hit_triangle(m, lay.tris, tri, ray, active, lay.far)
    closer = hit & ((t < t_best) | ((t == t_best) & _first_by_id(prim, prim_best, in_inst, hit_inst, instanced)))
    if instanced:
        hit_inst = dr.select(closer, in_inst, hit_inst)
    t_best = dr.select(closer, t, t_best)
    u_best = dr.select(closer, u, u_best)
    v_best = dr.select(closer, v, v_best)
    prim_best = dr.select(closer, prim, prim_best)
    if results is not None:
        if closer:  # (a branch: a packet where no lane found a closer hit skips the stores)
            for dst, src in ((results.t, t), (results.u, u), (results.v, v), (results.prim, prim)):
                dr.scatter(dst, src, slot, closer)
            if instanced:
                dr.scatter(results.inst, in_inst, slot, closer)
    return closer, t_best, u_best, v_best, prim_best, hit_inst


def _pop_global(m, stack: EntryStack, base, want, sp, e_link, e_t, n_stack, count_work: bool):
    """The next entry from the global entry stack (entries pushed by earlier steps, read, never
    written here) where `want` and the ray holds one: (from_global, sp, link, t, n_stack)."""
    from_global = want & (sp > 0)
    sp = dr.select(from_global, sp - 1, sp)
    e_link = dr.select(from_global, dr.gather(m.UInt32, stack.link, base + sp, from_global), e_link)
    e_t = dr.select(from_global, dr.gather(m.Float, stack.t, base + sp, from_global), e_t)
    if count_work:
        n_stack += dr.select(from_global, m.UInt32(1), m.UInt32(0))
    return from_global, sp, e_link, e_t, n_stack


# -- the instanced, bounded and push parts of the loop, one path each (a @dr.syntax piece's
# branches are Dr.Jit's; called from _walk's loop, every piece records into its kernel in the
# same order as when it was written inline: the kernels' IR is the same, hash for hash) --


@dr.syntax
def _leave_instance(m, want, link, in_inst, ray, world_o, world_d):
    """The LEAVE marker popped: the ray's instance is done; back to world space, next entry."""
    leave_inst = want & (link == LEAVE)
    link = dr.select(leave_inst, POP, link)
    if leave_inst:
        in_inst = m.UInt32(MISS)
        ray = setup_ray(m, world_o, world_d)
    return link, in_inst, ray


def _record_treelet(m, lay: DeviceLayout, link, n_treelet, count_work: bool, bounded: bool):
    """The treelet a compact state record's ray steps into (state.StateRecords): an exit link
    names it, a node link's is looked up (counted with the popped entries' lookups). Only a
    bounded step needs it; the tail's walk gets zeros. Returns (treelet, n_treelet)."""
    if not bounded:
        return dr.zeros(m.UInt32, dr.width(link)), n_treelet
    node = (link & EXIT_BIT) == 0
    tre = dr.select(node, dr.gather(m.UInt32, lay.node_treelet, link & PAYLOAD_MASK, node), link & PAYLOAD_MASK)
    if count_work:
        n_treelet += dr.select(node, m.UInt32(1), m.UInt32(0))
    return tre, n_treelet


def _entry_treelet(m, lay: DeviceLayout, treelet, want, active, link, from_global, n_treelet, count_work: bool):
    """A bounded step's popped entry: (whether it lies in another treelet than the step's,
    `treelet`, that treelet, the lookup count). Entries pushed in this step are of its treelet,
    exits excepted; global ones may be of any treelet (a node's is looked up, an exit names its own)."""
    other = want & active & (link != POP) & ((link & LEAF_BIT) == 0)
    is_exit = other & ((link & EXIT_BIT) != 0)
    tre = dr.select(is_exit, link & PAYLOAD_MASK, treelet)
    global_node = other & from_global & ~is_exit
    tre = dr.select(global_node, dr.gather(m.UInt32, lay.node_treelet, link & PAYLOAD_MASK, global_node), tre)
    if count_work:
        n_treelet += dr.select(global_node, m.UInt32(1), m.UInt32(0))
    return other & (tre != treelet), tre, n_treelet


@dr.syntax
def _enter_instance(m, lay: DeviceLayout, active, tri_cur, tri_end, link, in_inst, ray, world_o, world_d, n_enter,
                    next_treelet, count_work: bool, bounded: bool):
    """An instance link reached: into the instance's object space, on at its group's root (the
    caller pushes the LEAVE marker). A bounded step ends there: the group's root treelet is
    another treelet. Returns (entered, in_inst, ray, link, n_enter, next_treelet, active)."""
    entered = active & (tri_cur >= tri_end) & (link >= INSTANCE_TAG) & (link < LEAVE)
    if entered:
        in_inst = link & LEAF_FIRST_MASK
        enter_obj = to_object_space(m, lay.instances, in_inst, world_o, world_d, entered)
        ray = setup_ray(m, enter_obj.o, enter_obj.d)
        link = enter_obj.root
        if count_work:
            n_enter += 1
        if bounded:  # the group's root treelet is another treelet: this step ends here
            next_treelet = link & PAYLOAD_MASK
            active &= False
    return entered, in_inst, ray, link, n_enter, next_treelet, active


@dr.syntax
def _push_wide(m, loc_link, loc_t, nl, n_push, push_links, push_ts, cap: int):
    """A wide node's pushes: `n_push` entries, push_links/push_ts[j] to local stack position
    nl + n_push - 1 - j (j = 0 on top); the new count. A lane that pushes nothing writes the
    spare slot `cap`."""
    if n_push > 0:  # a packet where no lane pushes skips the K - 1 writes (lanes that
        # do not take this branch have n_push = 0 and would write the spare slot anyway)
        for j in range(len(push_links)):
            slot = dr.select(m.UInt32(j) < n_push, nl + n_push - (j + 1), cap)
            loc_link[slot] = push_links[j]
            loc_t[slot] = push_ts[j]
    return nl + n_push


@dr.syntax
def _push_binary(m, loc_link, loc_t, nl, push, far_link, far_t, cap: int):
    """A binary node's push of its farther child (where `push`) to the local stack; the new
    count. A lane that pushes nothing writes the spare slot `cap`."""
    slot = dr.select(push, nl, cap)
    loc_link[slot] = far_link
    loc_t[slot] = far_t
    return dr.select(push, nl + 1, nl)


def _wide_node(m, lay: DeviceLayout, node, ray, t_best, active):
    """A wide node's step: (link to go on with, or POP if no child is hit; how many entries to
    push; their links and entry distances, nearest first). The children are sorted by entry
    distance (misses last) with a sorting network: branch-free, as a SIMD lane must be."""
    fmt = node_format(lay.branching)
    hits, ts, links = hit_children_wide(m, lay.nodes, node, ray, t_best, active, fmt)
    keys = [dr.select(h, dr.minimum(t, _FLT_MAX), dr.inf) for h, t in zip(hits, ts)]
    n_hit = m.UInt32(0)
    for h in hits:
        n_hit += dr.select(h, m.UInt32(1), m.UInt32(0))
    for a, b in SORT_NETWORKS[fmt.branching]:
        swap = keys[b] < keys[a]
        keys[a], keys[b] = dr.select(swap, keys[b], keys[a]), dr.select(swap, keys[a], keys[b])
        links[a], links[b] = dr.select(swap, links[b], links[a]), dr.select(swap, links[a], links[b])
    link = dr.select(n_hit > 0, links[0], m.UInt32(POP))
    n_push = dr.select(n_hit > 1, n_hit - 1, m.UInt32(0))
    return link, n_push, tuple(links[1:]), tuple(keys[1:])


def _start_ray(m, lay: DeviceLayout, s: RayState, world_o, world_d):
    """Each ray where it starts: in the object space of the instance it is inside (s.inst, in an
    instanced layout), else in world space."""
    if lay.instances is None:
        return setup_ray(m, world_o, world_d)
    inside = s.inst != MISS
    obj = to_object_space(m, lay.instances, s.inst, world_o, world_d, inside)
    return setup_ray(m, [dr.select(inside, obj.o[c], world_o[c]) for c in range(3)],
                     [dr.select(inside, obj.d[c], world_d[c]) for c in range(3)])


def _first_by_id(prim, prim_best, inst, inst_best, instanced: bool):
    """Of two hits at the same t, whether (inst, prim) comes first: the lower instance, then the
    lower primitive (without instances: the lower primitive)."""
    if instanced:
        return (inst < inst_best) | ((inst == inst_best) & (prim < prim_best))
    return prim < prim_best
