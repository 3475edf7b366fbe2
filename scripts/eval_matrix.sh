#!/usr/bin/env bash
# Train (when missing) and evaluate the k-means bundle matrix on Lip6 Outdoor and the corridor
# validation sequence, then print one summary table. Every number in the README's results
# comes from this script.
#
#   scripts/eval_matrix.sh DATA BUNDLES RESULTS [NAME ...]
#
# DATA: the data root (train/, lip6_outdoor/, validation/corridor/); BUNDLES: where bundles are
# trained (BUNDLES/<name>, features cached in BUNDLES/cache); RESULTS: eval JSON, per-frame
# evidence (JSON lines) and failure images per bundle and sequence. NAME: bundles to run,
# <features>_kmeans_<words> (flat vocabulary) or <features>_kmeans_tree_<words> (vocabulary
# tree, branching 10) (default: the flat matrix); a bundle already in BUNDLES is evaluated as it
# is, whatever its name. Runs one job at a time; set PYTHON to
# choose the interpreter (default: python on PATH).
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,14p' "$0" >&2
  exit 2
fi
data=$1 bundles=$2 results=$3
shift 3
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(orb_kmeans_1000 orb_kmeans_2000 orb_kmeans_3000 orb_kmeans_5000 sift_kmeans_2000 sift_kmeans_3000)
py=${PYTHON:-python}
cli=("$py" -m aefabmap.cli.main)
mkdir -p "$bundles" "$results"

for name in "${names[@]}"; do
  features=${name%%_*}
  words=${name##*_}
  quantizer=kmeans
  case $name in *_kmeans_tree_*) quantizer=kmeans-tree ;; esac
  if [ ! -f "$bundles/$name/manifest.json" ]; then
    echo "== train $name" >&2
    "${cli[@]}" train --images "$data/train/camvid" "$data/train/scene15" --features "$features" \
      --quantizer "$quantizer" --words "$words" --seed 0 --out "$bundles/$name" --cache "$bundles/cache" --no-progress
  fi
  "$(dirname "$0")/eval_sequences.sh" "$data" "$bundles/$name" "$results/$name" \
    --frames "{out}.frames.jsonl" --failures "{out}.failures"
done
"$py" -m aefabmap_runtime.tools.results_table "$results"/*.json
