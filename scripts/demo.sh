#!/usr/bin/env bash
# The main job on the bundled sample data: set up, calibrate the sample session, scan the sample
# face, write a cleaned point cloud, a mesh and preview pictures into out/ (or $1).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
. "$root/scripts/setup.sh"
out="${1:-$root/out}"
mkdir -p "$out"
cd "$root"
echo "== 1/2 calibrate the sample session (calib_data/session) =="
gbcal calibrate calib_data/session -o "$out/calib.yaml"
echo "== 2/2 scan the sample face (calib_data/scan_head.png) =="
# --depth-range: the rig's working volume (mm); it also lets the indexing rule out far offsets
gbscan scan calib_data/scan_head.png --calib "$out/calib.yaml" -o "$out/cloud.ply" \
  --xyz "$out/xyz.npy" --mesh "$out/mesh.ply" --preview "$out/preview" --depth-range 400 1200
echo
echo "Done. Calibration: $out/calib.yaml"
echo "      Cloud:       $out/cloud.ply   Mesh: $out/mesh.ply   (open in MeshLab or Blender)"
echo "      Pictures:    $out/preview/"
