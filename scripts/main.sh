#!/usr/bin/env bash
# The main job (README): bootstrap, then the A/B comparison of the embedded default scene
# (scenes/bunny_box.xml: a diffuse Stanford bunny in the paper's box) against stock Mitsuba.
# Extra arguments go to `layerbvh compare` (e.g. --spp 64 --res 256 256 --traversal per_ray).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
exec .venv/bin/layerbvh compare scenes/bunny_box.xml --out out/compare_bunny_box "$@"
