#!/usr/bin/env bash
# The main job (README): bootstrap, then the traversal benchmark on the embedded default scene
# (the Stanford bunny in scenes/meshes). Extra arguments go to scripts/bench_traversal.py.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
mkdir -p out
exec .venv/bin/python scripts/bench_traversal.py --mesh scenes/meshes/bunny.ply --procedural-tris 0 \
  --rays 500000 --json out/bench_bunny.json "$@"
