#!/usr/bin/env bash
# Reproduce BENCHMARKS.md: the traversal benchmark on generated meshes, the recorded-ray grid and
# the error-vs-time run as `layerbvh sweep` grids (timed points one at a time), the scaling
# benchmark, and the report (about 26 minutes on 2 cores). Run after scripts/bootstrap.sh (or
# scripts/test.sh) has created .venv. SWEEP_ARGS="--scheduler ADDRESS" runs the grids on a Dask
# cluster instead of local worker processes (its machines need the repository at the same path).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
LAYERBVH=.venv/bin/layerbvh
SWEEP_ARGS=${SWEEP_ARGS:-}
$PY scripts/gen_stress.py spheres --triangles 1000000 --out out/stress_spheres_1m --force
# Generated meshes (the procedural sphere soup and the bunny are meshes, not scenes): one process.
$PY scripts/bench_traversal.py --branchings 2,4,8 --heights 4,8 --runs 5 --json docs/bench/bench_meshes.json
# What one walk-kernel iteration costs per branching (IR, packet-iterations, ns per packet-iteration).
$PY scripts/bench_kernel.py --rays 500000 --runs 9 --json docs/bench/kernel_cost.json
# Rays recorded from two scenes at 512x512, 4 spp (cached per scene): one point per scene and ray kind.
$LAYERBVH sweep scenes/paper_mix.xml out/stress_spheres_1m/scene.xml --job bench \
    --rays camera,first_bounce_diffuse,diffuse,glossy,specular,shadow --treelet-heights 4,8 --branchings 2,4,8 --runs 5 \
    --res 512 512 --spp 4 --rerun --out out/sweep_bench $SWEEP_ARGS
cp out/sweep_bench/bench.json docs/bench/bench.json
$PY scripts/bench_scaling.py --heights 4,8 --json docs/bench/scaling.json
# Error against time: one point per configuration, merged per scene by the sweep.
$LAYERBVH sweep scenes/paper_mix.xml --job converge --budget 40 --res 128 128 --ref-spp 4096 \
    --configs stock,embree,per_ray,layer_sorted:8,auto --rerun --out out/sweep_converge $SWEEP_ARGS
rm -rf docs/converge/paper_mix
cp -r out/sweep_converge/converge/paper_mix docs/converge/paper_mix
# auto against per_ray on whole renders of multi-shape scenes at their own depth, fresh processes
# (PERFORMANCE.md entry 25).
$PY scripts/bench_auto.py --rounds 3 --json docs/bench/auto_render.json
# The locality model (memory transactions and cache hits per mode) on both scenes' recorded rays
# (about 20 minutes on 2 cores; the 4-wide tree a render gets); BENCHMARKS.md's locality section.
$LAYERBVH sweep scenes/paper_mix.xml out/stress_spheres_1m/scene.xml --job locality \
    --rays camera,first_bounce_diffuse,diffuse,shadow --treelet-heights 4,8,12 --res 512 512 --spp 1 --workers 1 \
    --rerun --no-progress --out out/sweep_locality
cp out/sweep_locality/locality.json docs/bench/locality.json
# ... and against the warp (packet) width on the incoherent kinds (about 12 minutes).
$LAYERBVH sweep scenes/paper_mix.xml out/stress_spheres_1m/scene.xml --job locality --rays diffuse,shadow \
    --treelet-heights 8 --warp 8,16,32 --res 512 512 --spp 1 --workers 1 --rerun --no-progress --out out/sweep_locality_w
cp out/sweep_locality_w/locality.json docs/bench/locality_warps.json
# The locality model against valgrind's cache simulator on the real kernels (issue 41; about 6
# minutes; needs Debian's valgrind): its own section of BENCHMARKS.md, which report.py keeps.
# It exits 3 where the model disagrees with valgrind (issue 57 item 5): the section and the report
# are still written, then this script fails, naming it.
cachegrind=0
$PY scripts/check_model_cachegrind.py --mesh scenes/meshes/bunny.ply --rays 20000 --json docs/bench/cachegrind_bunny.json \
    || cachegrind=$?
$PY scripts/check_model_cachegrind.py --mesh procedural:600000 --rays 20000 --json docs/bench/cachegrind_procedural_600k.json \
    || cachegrind=$?
$PY scripts/check_model_cachegrind.py --report docs/bench/cachegrind_bunny.json docs/bench/cachegrind_procedural_600k.json
$PY scripts/report.py --bench docs/bench/bench_meshes.json --bench docs/bench/bench.json \
    --scaling docs/bench/scaling.json --converge docs/converge/paper_mix --locality docs/bench/locality.json \
    --locality docs/bench/locality_warps.json --readme
if [ "$cachegrind" != 0 ]; then
  echo "bench_all: the locality model disagrees with valgrind's cache simulator (check_model_cachegrind exit $cachegrind; BENCHMARKS.md's cachegrind section says where)" >&2
  exit "$cachegrind"
fi
