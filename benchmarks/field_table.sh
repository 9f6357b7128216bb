#!/usr/bin/env bash
# The field table of issue 10 (docs/RESULTS.md): every pbr set through `experiment images`
# with the field chain (dm+b, dm+r, dm+, dm, opnp) and with the paper's chain as written (dm-paper),
# then one table. Usage: benchmarks/field_table.sh DATA_DIR OUT_DIR [SET ...]
# (sets: folder names under DATA_DIR, e.g. pbr_sharp_s100 pbr_new_s200 pbr_worn_s300).
# EDGE_BREAK_MM=B declares the holders' break for the corner methods' verdict (--edge-break-mm;
# unset: not known; 0 for the sharp set).
set -euo pipefail
data=${1:?DATA_DIR}; out=${2:?OUT_DIR}; shift 2
sets=("$@")
CP=${CUTTERPOSE:-cutterpose}
brk=()
if [ -n "${EDGE_BREAK_MM:-}" ]; then brk=(--edge-break-mm "$EDGE_BREAK_MM"); fi
pairs=()
for s in "${sets[@]}"; do
  $CP experiment images "$data/$s" --methods dm+b,dm+r,dm+,dm,opnp --out "$out/$s" --workers 2 \
      "${brk[@]}" > /dev/null
  $CP experiment images "$data/$s" --methods dm-paper --chain as-written \
      --out "$out/${s}_paper" --workers 2 "${brk[@]}" > /dev/null
  pairs+=("$s=$out/$s" "${s}/paper-as-written=$out/${s}_paper")
done
$CP experiment field-table "${pairs[@]}" --out "$out"
