"""Canary for the private Dr.Jit calls the engine relies on (pinned drjit==1.5.0): a Dr.Jit upgrade that changes one
of them fails here, by name, before it silently changes a sort or a hit."""
from __future__ import annotations

import drjit as dr
import numpy as np

import layerbvh
from layerbvh import backend, wavefront

WHY = f"(drjit {dr.__version__}; layerbvh pins 1.5.0)"


def test_block_mkperm_is_a_stable_counting_sort():
    """wavefront.trace orders each step's rays with dr.detail.block_mkperm(keys, n, buckets): the
    permutation that sorts by key, equal keys in lane order (the order the step's records were
    written in)."""
    m = backend.module("llvm")
    rng = np.random.default_rng(7)
    keys = rng.integers(0, 13, 5000).astype(np.uint32)
    perm = np.array(dr.detail.block_mkperm(m.UInt32(keys), len(keys), 16))
    want = np.argsort(keys, kind="stable")
    assert perm.shape == want.shape and np.array_equal(perm, want), \
        f"dr.detail.block_mkperm no longer returns the stable counting sort the layer steps use {WHY}"


def test_import_tensor_aliases_the_memory_of_an_evaluated_array():
    """wavefront._alias: a second array over the same memory, no copy (walk writes its spill
    through it while reading the entry stack)."""
    m = backend.module("llvm")
    a = dr.zeros(m.UInt32, 64)
    dr.eval(a)
    b = wavefront._alias(a)
    dr.scatter(b, m.UInt32(7), m.UInt32(5))
    dr.eval(b)
    assert int(np.array(a)[5]) == 7, \
        f"dr.detail.import_tensor(a, False).array copies now: the step's spill would be lost {WHY}"


def test_the_llvm_target_symbols_are_exported():
    """backend reads and sets the LLVM target (ISA and lanes) through libdrjit-core's C++
    symbols jit_llvm_target_cpu/_features/_vector_width/_set_target (ctypes)."""
    width = layerbvh.llvm_vector_width()
    assert width in (4, 8, 16), f"jit_llvm_vector_width returned {width} {WHY}"
    assert layerbvh.llvm_isa() in ("avx2", "avx512", "other")
