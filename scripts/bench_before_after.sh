#!/usr/bin/env bash
# Before/after a change: `layerbvh compare` of the same scenes (128x128, 16 spp, per_ray) by the code
# at REV (a git worktree put ahead of the editable install on PYTHONPATH) and by the working tree,
# interleaved, two runs each. Prints the CPU, the vector width and each run's summary line.
# TRAVERSAL (default per_ray) picks the traversal of both sides.
#   bash scripts/bench_before_after.sh REV [SCENE ...]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
rev="${1:?usage: bench_before_after.sh REV [SCENE ...]}"; shift
scenes=("${@:-scenes/bunny_box.xml scenes/paper_mix.xml}")
work="$(mktemp -d)"
trap 'git -C "$root" worktree remove --force "$work/before" >/dev/null 2>&1 || true; rm -rf "$work"' EXIT
git -C "$root" worktree add -q --detach "$work/before" "$rev"
mkdir -p "$work/pp"
ln -s "$work/before/layerbvh" "$work/pp/layerbvh"
ln -s "$work/before/plugin" "$work/pp/layerbvh_mitsuba"
# Run from the scratch folder: `python -m` puts the current folder first on sys.path, so from the
# repository root the "before" side would import the working tree's layerbvh (it did, until
# issue 40: engine changes were compared with themselves).
scenes=($(cd "$root" && for sc in ${scenes[@]}; do realpath "$sc"; done))
cd "$work"
PY="$root/.venv/bin/python"
lscpu | grep -E "Model name|^CPU\(s\)"
$PY -c "import layerbvh; print('Dr.Jit LLVM lanes', layerbvh.llvm_vector_width())"
for scene in ${scenes[@]}; do
  for run in 1 2; do
    for side in before after; do
      pp=""; [ "$side" = before ] && pp="$work/pp"
      line=$(PYTHONPATH=$pp $PY -m layerbvh_mitsuba.cli compare "$scene" --res 128 128 --spp 16 --traversal "${TRAVERSAL:-per_ray}" \
             --out "$work/cmp_$side" --no-progress | sed -n 1p)
      echo "$scene run $run $side: $line"
    done
  done
done
