#!/usr/bin/env bash
# The `duplicates` pairs outside tests that ARCHITECTURE.md ("Repeats kept on purpose")
# names: the tracked files copied without tests/, crates/testkit, crates/fuzz, examples and
# benches, every `#[cfg(test)] mod` blanked (line numbers kept), then `duplicates` on the copy.
# `duplicates` is the project's tool-library command (not installed by CI).
set -euo pipefail
cd "$(dirname "$0")/.."
copy=$(mktemp -d)
trap 'rm -rf "$copy"' EXIT
git ls-files -co --exclude-standard |
  grep -v -E '^(tests/|crates/testkit/|crates/fuzz/)|/tests/|tests\.rs$|examples/|benches/' |
  while read -r f; do
    [ -f "$f" ] || continue
    mkdir -p "$copy/$(dirname "$f")"
    cp "$f" "$copy/$f"
  done
python3 - "$copy" <<'PY'
import os, re, sys
for root, _, files in os.walk(sys.argv[1]):
    for f in files:
        if not f.endswith(".rs"):
            continue
        p = os.path.join(root, f)
        lines = open(p).read().split("\n")
        for i, l in enumerate(lines):
            if l.strip() == "#[cfg(test)]" and i + 1 < len(lines) and re.match(
                r"\s*(pub(\(crate\))? )?mod \w+", lines[i + 1]
            ):
                lines = lines[:i] + [""] * (len(lines) - i)
                break
        open(p, "w").write("\n".join(lines))
PY
duplicates --repo "$copy" --most 200 --seconds 180 | sed "s|$copy/||g"
