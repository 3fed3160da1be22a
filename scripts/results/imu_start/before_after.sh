# usage: cmp.sh OUTFILE folder...
# The before/after pair of scripts/results/imu_start: every folder run by the commit before (a
# worktree at /tmp/w/base) and by this one, as written and without groundtruth.txt, scored by
# torchslam eval. scripts/bench_imu_start.py measures the current checkout alone.
source /work/main/.venv/bin/activate; export OMP_NUM_THREADS=1
out=$1; shift
for d in "$@"; do
  name=$(basename $d)
  ng=/tmp/w/nogt/$name; mkdir -p $ng
  for f in rgb depth rgb.txt depth.txt imu.txt calibration.txt; do ln -sfn $d/$f $ng/$f; done
  for tree in base main; do
    for mode in gt nogt; do
      src=$d; [ $mode = nogt ] && src=$ng
      o=/tmp/w/runs/$tree-$mode-$name
      (cd /tmp/w/$tree 2>/dev/null || cd /work/main; python -m torchslam run --system nislam --data $src --out $o --overwrite --no-tensorboard > $o.log 2>&1)
      ate=$(cd /work/main && torchslam eval --est $o/trajectory.txt --gt $d/groundtruth.txt --json | python -c "import json,sys; print(round(100*json.load(sys.stdin)['ate_rmse_m'],3))")
      loops=$(python -c "import json; d=json.load(open('$o/metrics.json')); l=d['loops']; print(l['accepted'], l['verified'])")
      warn=$(grep -c "not z-up" $o.log)
      echo "$name $tree $mode ate_cm=$ate loops_acc/ver=$loops zup_warn=$warn" | tee -a $out
    done
  done
done
