#!/usr/bin/env bash
# `make demo`: the main job of the project on whatever this checkout can do today.
# Usage: scripts/demo.sh CVSLAM_BIN SHARED_DATA_DIR DEMO_DIR
set -euo pipefail
cvslam="$1"; data="$2"; out="$3"
mkdir -p "$out"

if [ -d "$data/euroc_v101_micro/mav0" ]; then
  echo "== cvslam demo: import the real EuRoC V1_01 clip and inspect it"
  "$cvslam" import euroc "$data/euroc_v101_micro/mav0" -o "$out/euroc_v101.mcap" --vehicle uav1
  "$cvslam" info "$out/euroc_v101.mcap"
  if [ -d "$data/kitti_clip_a" ]; then
    echo
    echo "== cvslam demo: import the real KITTI clip a and inspect it"
    "$cvslam" import kitti "$data/kitti_clip_a" -o "$out/kitti_a.mcap" --vehicle car1
    "$cvslam" info "$out/kitti_a.mcap"
  fi
  echo
  echo "Logs written to $out/ (open them in Foxglove, or read them with rosbags)."
else
  echo "The real data folder $data is absent (set CVSLAM_SHARED_DATA or SHARED_DATA=...)."
fi
echo
echo "What this demo will do once the later stages land: simulate the two-UAV mission"
echo "(configs/scenarios/uav2_paper.yaml), run extract -> fuse (cooperative NH-infinity,"
echo "single and EKF for comparison) -> mosaic -> eval, and print the headline table and"
echo "the path of eval/report.html."
