#!/bin/bash
# A/B of the default against an older commit, one sweep variant at a time, alternating:
#   BASE_REV=<commit> OUT=<dir> benchmarks/bench_ab.sh [variant ...]
# For each variant (default: the sweep's three label maps and 60k points / 0.3 mm) it runs
# `ribpull bench --plan sweep --seeds 0 --variants V --no-skeleton-section --no-speed-section`
# from this working tree ("new", OUT/new-V) and then from a worktree of BASE_REV ("base",
# OUT/base-V, made once at OUT/base-tree), minutes apart; OUT/done.log lists each run's exit code.
# Both use this checkout's .venv. docs/bench_ab_*/ab_table.md tabulate such runs.
set -u
here=$(cd "$(dirname "$0")/.." && pwd)
out=${OUT:?set OUT}; base_tree=$out/base-tree
mkdir -p "$out"
[ -d "$base_tree" ] || git -C "$here" worktree add --detach "$base_tree" "${BASE_REV:?set BASE_REV}" >/dev/null
variants=("$@"); [ ${#variants[@]} -eq 0 ] && variants=(mask0.75x0.75x2.5mm-pv mask1.5mm-pv sternum-mask1.5mm-pv n60000-noise0.3)
for v in "${variants[@]}"; do
  for side in new base; do
    tree=$here; [ $side = base ] && tree=$base_tree
    (cd "$tree" && PYTHONPATH=$tree "$here/.venv/bin/python" -m ribpull_core.cli bench --plan sweep --seeds 0 --variants "$v" \
       --no-skeleton-section --no-speed-section -o "$out/$side-$v" > "$out/$side-$v.log" 2>&1)
    echo "$side $v rc=$?" >> "$out/done.log"
  done
done
echo ALLDONE >> "$out/done.log"
