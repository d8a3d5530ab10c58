"""The LLVM instruction set the kernels compile for can be chosen (LAYERBVH_LLVM_ISA, issue 64): an AVX-512 machine
checks a test's expectation as an AVX2 CPU gets it; a bad value is one line."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import layerbvh
from layerbvh import backend as be
from layerbvh import memmodel, meshes

_TRACE = """
import json, sys, numpy as np, layerbvh
from layerbvh import meshes
v, f = meshes.sphere_soup(40, 240, seed=3)
o, d = meshes.incoherent_rays(v, 20000, seed=5)
h = layerbvh.build(v, f, treelet_height=3).trace(o, d, mode="layer_sorted")
np.save(sys.argv[1], np.array(h.prim))
print(json.dumps({"isa": layerbvh.llvm_isa(), "lanes": layerbvh.llvm_vector_width()}))
"""


def _run(code: str, isa: str | None, *args) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != be.LLVM_ISA_ENV}
    if isa is not None:
        env[be.LLVM_ISA_ENV] = isa
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, env=env,
                          timeout=300)


@pytest.mark.skipif("avx2" not in memmodel.cpu_flags(), reason="this CPU has no AVX2")
def test_avx2_kernels_trace_the_same_hits(tmp_path):
    """LAYERBVH_LLVM_ISA=avx2: kernels compile for 8 lanes without AVX-512, and the traversal
    still returns the closest hits it returns at the CPU's own ISA (ties on shared edges may take
    the other triangle: at least 99.9% of the rays agree, measured 100%)."""
    r = _run(_TRACE, "avx2", tmp_path / "avx2.npy")
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"isa": "avx2", "lanes": 8}
    v, f = meshes.sphere_soup(40, 240, seed=3)
    o, d = meshes.incoherent_rays(v, 20000, seed=5)
    own = np.array(layerbvh.build(v, f, treelet_height=3).trace(o, d, mode="layer_sorted").prim)
    other = np.load(tmp_path / "avx2.npy")
    assert (own != layerbvh.MISS).mean() > 0.3, "the rays should hit the soup"
    assert (own == other).mean() >= 0.999, f"{(own != other).sum()} of {len(own)} rays differ between ISAs"


def test_an_isa_the_cpu_lacks_or_a_bad_name_is_one_line():
    """A name that is no ISA, or AVX-512 on a CPU without it, stops with one line naming the
    variable; AVX-512 on a CPU with it is taken."""
    bad = _run("import layerbvh", "avx3")
    assert bad.returncode != 0 and bad.stderr.strip().count("\n") == 0, bad.stderr
    assert "LAYERBVH_LLVM_ISA" in bad.stderr and "avx2, avx512" in bad.stderr and "Traceback" not in bad.stderr
    wide = _run("import layerbvh; print(layerbvh.llvm_isa(), layerbvh.llvm_vector_width())", "avx512")
    if "avx512f" in memmodel.cpu_flags():
        assert wide.returncode == 0 and wide.stdout.split() == ["avx512", "16"], wide.stderr
    else:
        assert wide.returncode != 0 and "has no avx512f" in wide.stderr and "Traceback" not in wide.stderr
