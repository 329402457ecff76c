#!/usr/bin/env bash
# Issue 67's check that a refactor changes no CPU model: trains the same small models with
# two builds of `stegongp` (same seed, data, options, thread count) and compares the files
# byte for byte, and their renders pixel for pixel (PNG bytes), and two generated scenes.
#
#   scripts/same_models.sh OLD_BINARY NEW_BINARY OUT_DIR [DATA_DIR]
#
# Models: lego plain (.ingp), fox-colmap plain (.msgpack), lego + text stego, the same with
# --stealth, with --robust, and a stego run killed after 12 steps (a --save-every state) and
# resumed to 24, and a plain run likewise (its state a checkpoint snapshot). A few minutes
# on two cores. Exit status 1 if any pair differs.
set -euo pipefail
old=$(realpath "$1"); new=$(realpath "$2"); out=$3; data=$(realpath "${4:-../shared/data}")
mkdir -p "$out"; out=$(realpath "$out")
base=(--batch 16384 --workers 2 --log2-t 15)
small=(--steps 24 "${base[@]}")
[ -d "$out/text" ] || "$old" synth --scene text --out "$out/text" --res 64 --train 20 --test 2 >/dev/null
[ -f "$out/k.key" ] || "$old" keygen --out "$out/k.key" >/dev/null
fail=0
same() { # name file_a file_b
  if cmp -s "$2" "$3"; then echo "same       $1"; else echo "DIFFERENT  $1"; fail=1; fi
}
for b in old new; do
  bin=${!b}; d="$out/$b"; mkdir -p "$d"
  cp "$out/k.key" "$d/k.key"; chmod 600 "$d/k.key"
  "$bin" train "$data/lego" --downscale 8 "${small[@]}" --out "$d/lego.ingp" 2>/dev/null
  "$bin" train "$data/fox-colmap" --downscale 8 "${small[@]}" --out "$d/fox.msgpack" 2>/dev/null
  for mode in default stealth robust; do
    extra=(); [ "$mode" = default ] || extra=(--"$mode")
    cp "$out/k.key" "$d/$mode.key"; chmod 600 "$d/$mode.key"
    "$bin" train "$data/lego" --downscale 8 "${small[@]}" --hidden "$out/text" \
      --key "$d/$mode.key" "${extra[@]}" --out "$d/$mode.ingp" 2>/dev/null
    "$bin" render --model "$d/$mode.ingp" --data "$out/text" --split test --views 1 \
      --key "$d/$mode.key" "${extra[@]}" --out "$d/$mode-hidden" >/dev/null 2>&1
  done
  "$bin" train "$data/lego" --downscale 8 --steps 12 "${base[@]}" \
    --hidden "$out/text" --key "$d/k.key" --save-every 4 --out "$d/killed.ingp" 2>/dev/null
  "$bin" train "$data/lego" --downscale 8 "${small[@]}" --hidden "$out/text" --key "$d/k.key" \
    --save-every 4 --resume "$d/killed.ingp.state" --out "$d/resumed.ingp" 2>/dev/null
  "$bin" train "$data/lego" --downscale 8 --steps 12 "${base[@]}" \
    --save-every 4 --out "$d/plain-killed.ingp" 2>/dev/null
  "$bin" train "$data/lego" --downscale 8 "${small[@]}" --save-every 4 \
    --resume "$d/plain-killed.checkpoint.msgpack" --out "$d/plain-resumed.ingp" 2>/dev/null
  "$bin" synth --scene object --res 48 --train 4 --test 1 --out "$d/synth-object" >/dev/null 2>&1
  "$bin" synth --scene room --aabb-scale 4 --res 48 --train 4 --test 1 --out "$d/synth-room" \
    >/dev/null 2>&1
  "$bin" render --model "$d/lego.ingp" --data "$data/lego" --split test --downscale 8 \
    --views 2 --out "$d/lego-render" >/dev/null 2>&1
done
for f in lego.ingp fox.msgpack default.ingp stealth.ingp robust.ingp resumed.ingp \
  plain-resumed.ingp; do
  same "$f" "$out/old/$f" "$out/new/$f"
done
for r in lego-render default-hidden stealth-hidden robust-hidden; do
  for png in "$out/old/$r"/*.png; do same "$r/$(basename "$png")" "$png" "$out/new/$r/$(basename "$png")"; done
done
for g in synth-object synth-room; do
  if diff -r -q "$out/old/$g" "$out/new/$g" >/dev/null; then echo "same       $g/"; else
    echo "DIFFERENT  $g/"; fail=1; fi
done
exit $fail
