#!/bin/bash
# Bench the sweep's label maps + 60k/0.3 on the working tree (new) and on 5d0c827 (base), one variant at a time, alternating.
out=/tmp/s48/bench; mkdir -p $out
for v in mask0.75x0.75x2.5mm-pv mask1.5mm-pv sternum-mask1.5mm-pv n60000-noise0.3; do
  for side in new base; do
    tree=/work/main; [ $side = base ] && tree=/tmp/s48/base
    (cd $tree && PYTHONPATH=$tree /work/main/.venv/bin/python -m ribpull_core.cli bench --plan sweep --seeds 0 --variants $v \
       --no-skeleton-section --no-speed-section -o $out/$side-$v > $out/$side-$v.log 2>&1)
    echo "$side $v rc=$?" >> $out/done.log
  done
done
echo ALLDONE >> $out/done.log
