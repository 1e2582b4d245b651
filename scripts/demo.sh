#!/usr/bin/env bash
# The demo: the main job on the bundled sample recording (samples/demo), outputs in out/demo/:
# the map, trajectories, exports (PLY, GLB, USDC), PNG previews, the HTML report and the
# evaluation against the sample's ground truth.
set -euo pipefail
cd "$(dirname "$0")/.."
PAPL=.venv/bin/papl-map
OUT=out/demo
mkdir -p "$OUT"
$PAPL run samples/demo/video.mp4 --camera samples/demo/camera.json --out "$OUT" \
    --export ply,glb,usdc --render --report --gt samples/demo
$PAPL info "$OUT/map.papl"
echo "demo: open $OUT/report.html (previews in $OUT/previews/, exports $OUT/map.*)"
