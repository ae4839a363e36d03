#!/usr/bin/env bash
# Render a short synthetic 8-camera sequence on built-in defaults (creates .venv and installs on first use).
# Extra arguments go to `torchtrack synth`.
source "$(dirname "$0")/_setup_venv.sh"
OUT="${OUT:-out/demo}"
.venv/bin/torchtrack synth --motion walk --duration 2 --out "$OUT/seq" "$@"
