#!/usr/bin/env bash
# dm+b with and without an edge look calibrated in the cell (docs/notes/edge_band.md,
# "Calibrating the look"): `experiment images --methods dm+b` on each set, plain and with
# --edge-look LOOK, then the field table and the budget's coverage.
# Usage: benchmarks/edge_look_table.sh LOOK.json DATA_DIR OUT_DIR [SET ...]
# (calibrate first: cutterpose calibrate-edge-look REFERENCE_SET --out LOOK.json, on a set
# rendered with seeds not in DATA_DIR's sets).
set -euo pipefail
look=${1:?LOOK.json}; data=${2:?DATA_DIR}; out=${3:?OUT_DIR}; shift 3
CP=${CUTTERPOSE:-cutterpose}
PY=${PYTHON:-python}
pairs=()
dirs=()
for s in "$@"; do
  [ -f "$out/$s/verdicts.csv" ] || $CP experiment images "$data/$s" --methods dm+b \
      --out "$out/$s" --workers 2 > /dev/null
  $CP experiment images "$data/$s" --methods dm+b --edge-look "$look" \
      --out "$out/${s}_cal" --workers 2 > /dev/null
  pairs+=("$s=$out/$s" "$s/calibrated=$out/${s}_cal")
  dirs+=("$out/$s" "$out/${s}_cal")
done
$CP experiment field-table "${pairs[@]}" --out "$out"
$PY "$(dirname "$0")/edge_look_coverage.py" "${dirs[@]}"
