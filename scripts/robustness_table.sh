#!/usr/bin/env bash
# The README's "What the hidden scene survives" table: lego ×4 (cover) + a generated text
# (hidden), one model per mode (plain, default stego, --stealth, --robust), every attack at
# its middle strength through `stegongp attack`, each file scored with `stegongp eval`
# (the hidden text with its key, the cover without). One JSON line per (mode, attack) in
# OUT/rows.jsonl; `benchmarks/robustness.md` has the table and the command.
#
#   scripts/robustness_table.sh OUT [STEPS] [EVAL_VIEWS] [FINETUNE_STEPS]
set -euo pipefail
out=${1:?usage: robustness_table.sh OUT [STEPS] [EVAL_VIEWS] [FINETUNE_STEPS]}
steps=${2:-300}
views=${3:-8}
ft=${4:-100}
bin=${STEGONGP:-target/release/stegongp}
lego=${LEGO:-../shared/data/lego}
mkdir -p "$out"
[ -d "$out/text" ] || "$bin" synth --scene text --res 200 --train 100 --test 25 --out "$out/text" >/dev/null
for mode in default stealth robust; do
  [ -f "$out/$mode.key" ] || "$bin" keygen --out "$out/$mode.key" >/dev/null 2>&1
done
train() { # mode
  local m=$1 extra=()
  case $m in
    plain) ;;
    default) extra=(--hidden "$out/text" --key "$out/default.key") ;;
    stealth) extra=(--hidden "$out/text" --key "$out/stealth.key" --stealth) ;;
    robust) extra=(--hidden "$out/text" --key "$out/robust.key" --robust) ;;
  esac
  [ -f "$out/$m.ingp" ] || "$bin" train "$lego" --downscale 4 --steps "$steps" "${extra[@]}" \
    --out "$out/$m.ingp" --json > "$out/$m.train.json"
}
score() { # model data [args…] → "psnr ssim blank_psnr"
  local model=$1 data=$2; shift 2
  "$bin" eval --model "$model" --data "$data" --views "$views" --no-lpips --json "$@" 2>/dev/null |
    python3 -c 'import json,sys; d=json.load(sys.stdin); print(d["psnr"], d["ssim"], d["blank_psnr"])'
}
# ATTACKS (space-separated) overrides the list; a (mode, attack) already in rows.jsonl is
# not measured again, so a stopped run goes on where it was.
if [ -n "${ATTACKS:-}" ]; then
  read -r -a attacks <<<"none $ATTACKS"
else
  attacks=(none "noise=0.001" "noise=0.005" "prune=0.15" "prune-magnitude=0.15" "quantise=8"
    "quantise=4" purify "purify-contribution=1e-7" "purify-mlp=$ft" "finetune=$ft"
    "finetune-renders=$ft" "redistil=$((ft * 3))")
fi
touch "$out/rows.jsonl"
for mode in ${MODES:-plain default stealth robust}; do
  train $mode
  hidden_args=()
  case $mode in
    stealth) hidden_args=(--key "$out/stealth.key" --stealth) ;;
    default|robust) hidden_args=(--key "$out/$mode.key") ;;
  esac
  for a in "${attacks[@]}"; do
    if grep -qF "\"mode\":\"$mode\",\"attack\":\"$a\"," "$out/rows.jsonl"; then
      continue
    fi
    tag=$(echo "$a" | tr '=' '_')
    f="$out/$mode.$tag.ingp"
    secs=0
    if [ "$a" = none ]; then
      f="$out/$mode.ingp"
    elif [ ! -f "$f" ]; then
      t0=$(date +%s.%N)
      "$bin" attack "$out/$mode.ingp" --out "$f" "$a" --data "$lego" --downscale 4 --json > "$out/$mode.$tag.json"
      secs=$(python3 -c "import time; print(round(time.time() - $t0, 1))")
    fi
    read -r cp cs cb <<<"$(score "$f" "$lego" --downscale 4)"
    hp=null; hs=null; hb=null
    if [ $mode != plain ]; then
      read -r hp hs hb <<<"$(score "$f" "$out/text" "${hidden_args[@]}")"
    fi
    echo "{\"mode\":\"$mode\",\"attack\":\"$a\",\"cover_psnr\":$cp,\"cover_ssim\":$cs,\"cover_blank\":$cb,\"hidden_psnr\":$hp,\"hidden_ssim\":$hs,\"hidden_blank\":$hb,\"attack_seconds\":$secs}" | tee -a "$out/rows.jsonl"
  done
done
# The table: a row per attack, hidden / cover PSNR per mode (hidden erased: ≤ 1 dB above
# the empty render's PSNR, marked ✗).
python3 - "$out/rows.jsonl" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
modes = [m for m in ["plain", "default", "stealth", "robust"] if any(r["mode"] == m for r in rows)]
attacks = list(dict.fromkeys(r["attack"] for r in rows))
print("| attack | " + " | ".join(f"{m} hidden / cover" if m != "plain" else "plain cover" for m in modes) + " |")
print("|---" * (len(modes) + 1) + "|")
for a in attacks:
    cells = []
    for m in modes:
        r = next((r for r in rows if r["mode"] == m and r["attack"] == a), None)
        if r is None:
            cells.append("")
        elif r["hidden_psnr"] is None:
            cells.append(f"{r['cover_psnr']:.2f}")
        else:
            gone = " ✗" if r["hidden_psnr"] <= r["hidden_blank"] + 1.0 else ""
            cells.append(f"{r['hidden_psnr']:.2f}{gone} / {r['cover_psnr']:.2f}")
    print(f"| {a} | " + " | ".join(cells) + " |")
PY
