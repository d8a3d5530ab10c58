#!/usr/bin/env python3
"""What drjit's dr.freeze (1.5.0) accepts, probed on its own (PERFORMANCE.md entry 54, issue 57 item 4):
the facts the frozen wavefront steps (layerbvh/wavefront.py) are built around. Each probe runs in
its own process (some crash it) and prints one line; about 10 s in all.

    .venv/bin/python scripts/freeze_probe.py [--backend llvm|cuda]
"""
from __future__ import annotations

import argparse
import subprocess
import sys

PRELUDE = """
import drjit as dr, numpy as np
from drjit.{backend} import Float, UInt32, Bool
"""

PROBES = {
    "widths, loop, local array": ("a frozen function with a symbolic loop, a local array and a masked scatter replays "
                                  "correctly at other widths", """
def body(data, idx, out):
    x = dr.gather(Float, data, idx)
    loc = dr.alloc_local(Float, 4, Float(0))
    i, acc, _ = dr.while_loop((UInt32(0) * idx, dr.zeros(Float, dr.width(idx)), x),
                              lambda i, acc, x: i < 5 + (idx & 3), lambda i, acc, x: (i + 1, acc + x * 0.5, x))
    dr.scatter(out, acc, idx, acc > 1)
    return acc
f = dr.freeze(body)
ok = True
data = dr.arange(Float, 1000) * 0.01
for n in (1000, 700, 333, 1000, 12):
    idx = dr.arange(UInt32, n) * 3 % 1000
    a, b = dr.zeros(Float, 1000), dr.zeros(Float, 1000)
    r1 = body(data, idx, a); r2 = f(data, idx, b); dr.eval(r1, r2, a, b)
    ok &= np.array_equal(np.asarray(r1), np.asarray(r2)) and np.array_equal(np.asarray(a), np.asarray(b))
print(ok)
"""),
    "block_mkperm": ("dr.detail.block_mkperm (the layer steps' sort) inside a frozen function, at other widths", """
f = dr.freeze(lambda keys: dr.detail.block_mkperm(keys, dr.width(keys), 16))
ok = True
for n in (1000, 700, 333):
    keys = (dr.arange(UInt32, n) * 7919) % 13
    dr.eval(keys)
    p = f(keys); q = dr.detail.block_mkperm(keys, n, 16)
    ok &= np.array_equal(np.asarray(p), np.asarray(q))
print(ok)
"""),
    "read and write one array": ("a kernel that gathers from and scatters into one input array: Dr.Jit copies it "
                                 "(the frozen step's entry stack), correctly at other widths", """
def body(t, idx):
    x = dr.gather(Float, t, idx)
    dr.scatter(t, x * 2 + 1, idx + 1, idx % 7 == 0)
f = dr.freeze(body)
ok, copied = True, True
for n in (100, 100000, 1000):
    t = dr.arange(Float, 2 * n); idx = dr.arange(UInt32, n) * 2; dr.eval(t, idx)
    ref = np.arange(2 * n, dtype=np.float32); i = idx.numpy(); m = i % 7 == 0; ref[(i + 1)[m]] = ref[i[m]] * 2 + 1
    before = t.index
    f(t, idx); dr.eval(t)
    ok &= np.array_equal(np.asarray(t), ref); copied &= t.index != before
print(ok and copied)
"""),
    "allocation sized by dr.width": ("an array allocated inside with a size from dr.width keeps the recorded size "
                                     "on replay (False or a crash: why StateRecords.write takes `into`)", """
def body(x):
    n = dr.width(x)
    rec = dr.empty(UInt32, n * 4)
    dr.scatter(rec, UInt32(x) + 1, dr.arange(UInt32, n) * 4)
    return rec
f = dr.freeze(body)
ok = True
for n in (100, 1000):
    x = dr.arange(Float, n); dr.eval(x)
    r = f(x); dr.eval(r)
    ok &= dr.width(r) == 4 * n
print(ok)
"""),
    "a changed bool in the key": ("a keyword bool that changes between calls, where the same True and False "
                                  "objects also sit elsewhere in the arguments, records again (False: drjit's key "
                                  "visits each Python object once by identity and missed it; why wavefront.py "
                                  "states the key itself, state_fn)", """
from dataclasses import dataclass
@dataclass
class Lay:
    a: object
    far: bool
def body(lay, x, *, instanced, flag):
    y = dr.gather(Float, lay.a, UInt32(0) * UInt32(x))
    return y * x * 2 if flag else y * x * 3
f = dr.freeze(body)
lay = Lay(dr.arange(Float, 4) + 1, True)
x = dr.arange(Float, 4)
a, b = f(lay, x, instanced=False, flag=True), f(lay, x, instanced=False, flag=False)
print(np.array_equal(np.asarray(b), np.asarray(x) * 3))
"""),
    "alias over an input's memory": ("a second array over an input's memory (import_tensor, the unfrozen step's "
                                     "spill) passed in: this small case runs, the wavefront step with it crashed "
                                     "(signal 11, entry 54), so frozen steps spill into the stack", """
def body(a, alias, idx):
    x = dr.gather(UInt32, a, idx)
    dr.scatter(alias, x + 1, idx + 1)
f = dr.freeze(body)
a = dr.arange(UInt32, 64); dr.eval(a)
alias = dr.detail.import_tensor(a, False).array
f(a, alias, dr.arange(UInt32, 32) * 2); dr.eval(a)
print(True)
"""),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", choices=("llvm", "cuda"), default="llvm")
    a = ap.parse_args(argv)
    for name, (what, code) in PROBES.items():
        p = subprocess.run([sys.executable, "-c", PRELUDE.format(backend=a.backend) + code], capture_output=True,
                           text=True, timeout=300)
        out = p.stdout.strip().splitlines()
        got = ("crashed (signal %d)" % -p.returncode if p.returncode < 0 else
               out[-1] if out else "error: " + (p.stderr.strip().splitlines() or ["?"])[-1][:120])
        print(f"{name:30s} {got:20s} {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
