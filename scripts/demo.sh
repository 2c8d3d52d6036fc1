#!/usr/bin/env bash
# `make demo`: simulate the paper's two-UAV mission and run every stage on it.
# Usage: scripts/demo.sh CVSLAM_BIN SHARED_DATA_DIR DEMO_DIR
set -euo pipefail
cvslam="$1"; data="$2"; out="$3"
mkdir -p "$out"
start=$(date +%s)

echo "== cvslam demo: simulate the two-UAV mission (configs/scenarios/uav2_paper.yaml)"
"$cvslam" simulate uav2_paper -o "$out/sim" --force
echo
echo "== cvslam demo: cvslam run = extract, fuse (cooperative NH-infinity; each UAV alone;"
echo "   the EKF), mosaic, eval"
"$cvslam" run "$out/sim/uav1.mcap" "$out/sim/uav2.mcap" -o "$out/run" --force
echo
echo "== cvslam demo: done in $(( $(date +%s) - start )) s"
echo "Position error (ATE RMSE, m, against the simulator's ground truth, no alignment) per UAV:"
echo "cooperative NH-infinity vs each UAV alone (single) vs the cooperative EKF vs dead reckoning."
"$(dirname "$cvslam")/python" -c 'import sys, pandas as pd
print(pd.read_csv(sys.argv[1], index_col=0).round(2).to_string())' "$out/run/eval/headline.csv"
echo
echo "Report:   $out/run/eval/report.html (one self-contained page: open it in a browser)"
echo "Metrics:  $out/run/eval/metrics.csv, metrics.json"
echo "Mosaics:  $out/run/mosaic/{uav1,uav2,all}.png (+ .pgw world files, *_overlay.png)"
echo "Outputs:  $out/run/fuse*/ (trajectories, map, timeline, result.mcap for Foxglove);"
echo "          logs and ground truth in $out/sim"
if [ -d "$data" ]; then
  echo "Real data: see README (cvslam import euroc|kitti on $data)."
fi
