#!/usr/bin/env bash
# Train (when missing) and evaluate autoencoder (AE-VQ) bundles on Lip6 Outdoor and the corridor
# validation sequence, like scripts/eval_matrix.sh does for k-means. Every AE number in
# docs/results.md comes from this script.
#
#   scripts/ae_matrix.sh DATA BUNDLES RESULTS NAME [NAME ...]
#
# NAME: <features>_ae_<variant>_<words>, variant one of
#   light       light MLP encoder, reconstruction only
#   lightmatch  light MLP encoder + matching term (weight $MATCH_WEIGHT, default 0.1)
#   paper       the paper's 1-D conv stack, reconstruction only
# Budget: $AE_BUDGET_S s of AE training wall time (default 600), early stopping with patience 3
# on a held-out 5 % of 250 000 training descriptors; matching pairs from 600 homography warps and
# 400 consecutive CamVid frame pairs (15 % of them held out). One thread everywhere (on a loaded
# 2-core machine a second thread slows training down). Evaluates the int8 graph.
set -euo pipefail
if [ $# -lt 4 ]; then
  sed -n '2,16p' "$0" >&2
  exit 2
fi
data=$1 bundles=$2 results=$3
shift 3
py=${PYTHON:-python}
cli=("$py" -m aefabmap.cli.main)
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$bundles" "$results"
for name in "$@"; do
  IFS=_ read -r features ae variant words <<<"$name"
  [ "$ae" = ae ] || { echo "not an AE bundle name: $name" >&2; exit 2; }
  if [ ! -f "$bundles/$name/manifest.json" ]; then
    case $variant in
      light) extra=(--ae-arch light) ;;
      lightmatch) extra=(--ae-arch light --ae-match-weight "${MATCH_WEIGHT:-0.1}") ;;
      paper) extra=(--ae-arch paper) ;;
      *) echo "unknown AE variant $variant (bundles made otherwise, e.g. by ae_tree_bundle.py, are only evaluated)" >&2; exit 2 ;;
    esac
    echo "== train $name" >&2
    "${cli[@]}" train --images "$data/train/camvid" "$data/train/scene15" --features "$features" \
      --quantizer ae --ae-objective recon --words "$words" --seed 0 --max-descriptors 250000 --ae-descriptors 250000 \
      --ae-epochs 200 --ae-patience 3 --ae-budget-s "${AE_BUDGET_S:-600}" --ae-threads 1 \
      --ae-warp-images 600 --ae-frame-pairs 400 "${extra[@]}" \
      --out "$bundles/$name" --cache "$bundles/cache" --no-progress
  fi
  "$(dirname "$0")/eval_sequences.sh" "$data" "$bundles/$name" "$results/$name" --variant int8
done
