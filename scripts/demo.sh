#!/usr/bin/env bash
# `make demo`: the main job of the project with the stages that exist today.
# Usage: scripts/demo.sh CVSLAM_BIN SHARED_DATA_DIR DEMO_DIR
set -euo pipefail
cvslam="$1"; data="$2"; out="$3"
mkdir -p "$out"

echo "== cvslam demo: simulate the two-UAV mission (configs/scenarios/uav2_paper.yaml)"
"$cvslam" simulate uav2_paper -o "$out/sim" --force
"$cvslam" info "$out/sim/uav1.mcap" "$out/sim/uav2.mcap"
echo
echo "== cvslam demo: adaptive SIFT + stereo-constrained matching on every frame"
"$cvslam" extract "$out/sim/uav1.mcap" "$out/sim/uav2.mcap" -o "$out/run" --force

if [ -d "$data/euroc_v101_micro/mav0" ]; then
  echo
  echo "== cvslam demo: import the real EuRoC V1_01 clip and inspect it"
  "$cvslam" import euroc "$data/euroc_v101_micro/mav0" -o "$out/euroc_v101.mcap" --vehicle uav1
  "$cvslam" info "$out/euroc_v101.mcap"
else
  echo "(the real data folder $data is absent: skipping the EuRoC import)"
fi
echo
echo "Logs and ground truth are in $out/sim (open the .mcap files in Foxglove or read them"
echo "with rosbags); features in $out/run/features. Still to land: fuse (cooperative"
echo "NH-infinity, single and EKF for comparison) -> mosaic -> eval, the headline table and"
echo "eval/report.html."
