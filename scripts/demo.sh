#!/usr/bin/env bash
# The main job on built-in defaults (creates .venv and installs on first use): render a synthetic 8-camera
# walk, track it markerlessly and print the error against its ground truth.
# Extra arguments go to `torchtrack track` (e.g. --model hull, --device cuda).
set -euo pipefail
source "$(dirname "$0")/_setup_venv.sh"
OUT="${OUT:-out/demo}"
# rendered once; again when the body model (configs/body.urdf, blobs.yaml) has changed since
.venv/bin/torchtrack synth --motion walk --duration 2 --out "$OUT/seq" --reuse
.venv/bin/torchtrack track "$OUT/seq" --out "$OUT/track" --overwrite "$@"  # replaces the last demo's track
.venv/bin/torchtrack eval "$OUT/track/poses.npz" "$OUT/seq/gt.npz"
echo "TensorBoard: .venv/bin/tensorboard --logdir $OUT/track/tb"
