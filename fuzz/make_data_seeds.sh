#!/usr/bin/env bash
# Writes the seed corpus of the fuzz targets of arkit-data's and arkit-perspnet's
# readers (crop_part, crop_window, mesh, crops_json, dataset_json, conversion_json,
# checkpoint_json, perspnet_json) into fuzz/corpus/<target>/: real files written by
# the tool from `synth` data (a tiny release: 2 subjects x 2 images of 128x128, converted
# in shards of one row and as two parts, crop stores of side 16 in each codec, a model
# trained for one step), then the truncated, bit-flipped and hostile variants that
# the examples `data_fuzz_seeds` and `perspnet_fuzz_seeds` derive from them. Deterministic (fixed seeds)
# but for the absolute paths and times the JSON files record.
#
#   cargo build --release --workspace --locked --bins --examples
#   bash fuzz/make_data_seeds.sh            # about 20 s
# (built with --workspace: `cargo run -p` alone would build polars with other features.)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${ARKIT_TOOL_BIN:-target/release/arkit-tool}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
q() { "$bin" "$@" >/dev/null; }
q synth --output "$work/release" --subjects 2 --images-per-subject 2 --size 128x128 --seed 5
q convert --input "$work/release" --output "$work/pq" --rows-per-shard 1
for i in 0 1; do
  q convert --input "$work/release" --output "$work/parts" --rows-per-shard 1 --shard "$i/2"
done
for codec in raw png pred-zstd; do
  q crops --dataset "$work/pq" --size 16 --codec "$codec" --output "$work/crops-$codec"
done
q render --dataset "$work/pq" --size 64 --points 256 --uv-size 32 --overwrite
q train --dataset "$work/pq" --split all --steps 1 --batch 1 --config tiny --output "$work/model"
examples=$(dirname "$bin")/examples
"$examples/data_fuzz_seeds" "$work" fuzz/corpus
"$examples/perspnet_fuzz_seeds" "$work/model" fuzz/corpus
du -sh fuzz/corpus/{crop_part,crop_window,mesh,crops_json,dataset_json,conversion_json,checkpoint_json,perspnet_json}
