#!/usr/bin/env bash
# Evaluate one bundle on Lip6 Outdoor (the protocol's exclusion window, 50) and the corridor
# validation sequence (its README's window, 20), raw score LLR. The one place the matrix
# scripts (eval_matrix.sh, ae_matrix.sh) define the sequences and their windows.
#
#   scripts/eval_sequences.sh DATA BUNDLE OUT_PREFIX [EVAL OPTION ...]
#
# Writes OUT_PREFIX_lip6.json and OUT_PREFIX_corridor.json; "{out}" in an option is replaced by
# OUT_PREFIX_<sequence> (e.g. --frames {out}.frames.jsonl). PYTHON chooses the interpreter.
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,9p' "$0" >&2
  exit 2
fi
data=$1 bundle=$2 prefix=$3
shift 3
py=${PYTHON:-python}
for seq in lip6:lip6_outdoor/ground_truth.npy:50 corridor:validation/corridor/gt.npy:20; do
  IFS=: read -r tag gt exclude <<<"$seq"
  images=$data/$(dirname "$gt")
  [ "$tag" = corridor ] && images=$data/validation/corridor/images
  out=${prefix}_$tag
  extra=()
  for opt in "$@"; do extra+=("${opt//\{out\}/$out}"); done
  echo "== eval $(basename "$bundle") on $tag" >&2
  "$py" -m aefabmap.cli.main eval --model "$bundle" --images "$images" --gt "$data/$gt" --exclude "$exclude" \
    --fabmap-score llr --json "$out.json" --no-progress "${extra[@]}"
done
