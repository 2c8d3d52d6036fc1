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
echo
echo "== cvslam demo: the filter, cooperative NH-infinity, then each UAV alone and the EKF"
"$cvslam" fuse "$out/run" --force
"$cvslam" fuse "$out/run" --single --force
"$cvslam" fuse "$out/run" --filter ekf --force
echo
echo "== cvslam demo: ground mosaics from the fused poses, per UAV and merged"
"$cvslam" mosaic "$out/run" --force

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
echo "with rosbags); features in $out/run/features; trajectories, map, timeline and"
echo "result.mcap in $out/run/fuse (cooperative), fuse_single, fuse_ekf; mosaics (PNG + world"
echo "files, overlays) in $out/run/mosaic. Still to land: eval, the headline table and"
echo "eval/report.html."
