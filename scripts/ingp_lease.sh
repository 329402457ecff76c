#!/usr/bin/env bash
# instant-ngp beside StegoNGP on one lent GPU (issue 57, item 2). Run in the repository root
# on the machine with the GPU, with what was prepared here carried along:
#   .carry        scripts/gpu_bench.py prepare .carry   (our binary, lego at 800 px as lossless
#                 WebP with 8 test views, the Vulkan loader)
#   .carry-ingp   scripts/ingp_pack.sh                  (instant-ngp's source, headless)
#   .ingp-build   optional: a build an earlier lease brought back (`ingp_lease.sh join`)
#
#   scripts/ingp_lease.sh OUT [PHASE...]      (default phases: build ingp ours cross)
#   scripts/ingp_lease.sh join RESULTS        (here: the build's parts into .ingp-build/)
#
# Phases (each appends to OUT/ingp_lease.json, rewritten as it goes, and OUT/log.txt):
#   check  needs no GPU or CUDA: unpacks the source and configures and compiles what of it
#          does not need CUDA (below); run it here before a lease.
#   build  unpacks instant-ngp; configures it headless (no GUI, OptiX, Vulkan/DLSS; Python
#          bindings on) for the card's architecture (nvidia-smi's compute capability, 90 on
#          an H200) with CMake and ninja; builds pyngp and the instant-ngp executable; writes
#          the stripped build to OUT in parts of at most 15 MiB. With .ingp-build/ carried,
#          unpacks that instead of compiling.
#   ingp   instant-ngp trains lego at 800 px for MINUTES (default 5) as scripts/run.py trains
#          by default, a snapshot each minute; each snapshot's test views scored under
#          run.py's protocol (scripts/ingp_driver.py); ours loads the last snapshot and
#          scores it under the same protocol.
#   ours   stegongp trains the same lego for MINUTES (train --device gpu --checkpoints
#          1..MINUTES --eval-protocol instant-ngp): PSNR each minute under the same protocol,
#          steps/s and samples a step.
#   cross  a 1-minute lego + text stego pair (a prf key); our plain (from `ours`, run first
#          if this call has not) and stego files rendered by us (`eval --protocol
#          instant-ngp --out`) and loaded and rendered by instant-ngp, scored against the
#          ground truth and against our renders.
# Budget: the phases' minutes (2·MINUTES + ~3 + the build) exceed one 10-minute command,
# and nothing outlives a call but what OUT brings back: give each call the phases that fit,
# e.g. `build ingp` in one and `build ours cross` in another (benchmarks/gpu.md, "instant-ngp
# on the lent card").
set -uo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
CARRY=${CARRY:-$REPO/.carry}
INGP=${INGP:-$REPO/.carry-ingp}
PREBUILT=${PREBUILT:-$REPO/.ingp-build}
MINUTES=${MINUTES:-5}
WORK=${WORK:-/tmp/ingp_lease}
PART=$((15 * 1024 * 1024))
# CMake 4 refuses projects that ask for compatibility below 3.5 (zlib's does) unless told.
COMPAT=-DCMAKE_POLICY_VERSION_MINIMUM=3.5

die() { echo "ingp_lease: error: $*" >&2; exit 1; }

if [ "${1:-}" = join ]; then
    RES=${2:?join RESULTS: the OUT folder a build lease brought back}
    ls "$RES"/ingp-build.tar.xz.part* > /dev/null 2>&1 || die "$RES: no ingp-build.tar.xz.part*"
    mkdir -p "$PREBUILT"
    cat $(ls "$RES"/ingp-build.tar.xz.part* | sort -V) > "$PREBUILT/ingp-build.tar.xz"
    want=$(cat "$RES/ingp-build.sha256")
    got=$(sha256sum "$PREBUILT/ingp-build.tar.xz" | cut -d' ' -f1)
    [ "$want" = "$got" ] || die "the parts do not make the build the lease wrote"
    echo "$PREBUILT/ingp-build.tar.xz: $(stat -c %s "$PREBUILT/ingp-build.tar.xz") bytes, sha256 ok"
    exit 0
fi

OUT=${1:?usage: scripts/ingp_lease.sh OUT [build] [ingp] [ours] [cross]}
shift
PHASES=${*:-build ingp ours cross}
mkdir -p "$OUT" "$WORK"
LOG=$OUT/log.txt
JSON=$OUT/ingp_lease.json
T0=$(date +%s)
SRC=$WORK/instant-ngp
BUILD=$SRC/build
BIN=$WORK/stegongp
LEGO=$WORK/lego
DRIVER=(python3 "$REPO/scripts/ingp_driver.py" --build "$BUILD" --src "$SRC")

note() { echo "[$(( $(date +%s) - T0 )) s] $*" | tee -a "$LOG" >&2; }

# Records VALUE (JSON text, or a file holding it) under KEY in OUT/ingp_lease.json.
record() {
    python3 - "$JSON" "$1" "$2" <<'PY'
import json, os, sys
path, key, val = sys.argv[1:]
r = json.load(open(path)) if os.path.exists(path) else {}
if os.path.isfile(val):
    val = open(val).read()
try:
    r[key] = json.loads(val)
except ValueError:
    r[key] = val
json.dump(r, open(path + ".tmp", "w"), indent=1)
os.replace(path + ".tmp", path)
PY
}

# Runs a command, its stderr to the log, and returns its status (the caller decides whether
# a failure ends the run).
run() {
    note "+ $*"
    "$@" 2>> "$LOG"
}

# `run` for a command whose output is only worth keeping in the log (a build's).
quiet() {
    note "+ $*"
    "$@" >> "$LOG" 2>&1
}

setup_ours() {
    [ -x "$BIN" ] && return 0
    [ -f "$CARRY/stegongp.xz" ] || die "$CARRY/stegongp.xz: run scripts/gpu_bench.py prepare .carry here first"
    # The loader, the binary and lego's PNGs, as gpu_bench.py's run prepares them.
    python3 - "$CARRY" "$WORK" <<'PY' 2>> "$LOG" || die "setting up our binary and lego failed (log.txt)"
import lzma, os, shutil, sys
from pathlib import Path
sys.path.insert(0, os.path.join(os.environ.get("REPO", "."), "scripts"))
import gpu_bench as g
carry, work = Path(sys.argv[1]), Path(sys.argv[2])
debs = sorted((carry / "gl").glob("*.deb"))
# Unpacked into / only on the GPU machine, and only where it lacks the loader.
if debs and shutil.which("nvidia-smi") and not g.has_vulkan_loader():
    import subprocess
    for d in debs:
        subprocess.run(["dpkg", "-x", str(d), "/"], check=True)
    subprocess.run(["ldconfig"], check=True)
(work / "stegongp").write_bytes(lzma.open(carry / "stegongp.xz").read())
(work / "stegongp").chmod(0o755)
print(g.expand_scene(carry / "lego", work / "lego"), "images", file=sys.stderr)
PY
    [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] \
        && export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    run "$BIN" devices --require-hardware --json > "$WORK/devices.json" \
        || die "no hardware adapter for our binary (log.txt)"
    record devices "$WORK/devices.json"
}

phase_build() {
    [ -f "$INGP/ingp-src.tar.xz" ] || die "$INGP/ingp-src.tar.xz: run scripts/ingp_pack.sh here first"
    rm -rf "$SRC"
    tar -C "$WORK" -xJf "$INGP/ingp-src.tar.xz" || die "unpacking instant-ngp failed"
    record source "$INGP/ingp-src.json"
    if [ -f "$PREBUILT/ingp-build.tar.xz" ]; then
        mkdir -p "$BUILD" && tar -C "$BUILD" -xJf "$PREBUILT/ingp-build.tar.xz"
        note "instant-ngp: the carried build unpacked"
        record build '{"prebuilt": true}'
        return 0
    fi
    local cc arch zlib=() t
    cc=$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader 2>/dev/null | head -1 | tr -d ' .')
    arch=${ARCH:-${cc:-90}}
    # zstr needs zlib; build the carried source where the image has no zlib.h.
    if [ ! -f /usr/include/zlib.h ]; then
        quiet cmake -S "$SRC/dependencies/zlib" -B "$WORK/zlib-build" -G Ninja "$COMPAT" \
            -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$WORK/zlib" \
            && quiet cmake --build "$WORK/zlib-build" --target install \
            || die "building the carried zlib failed"
        zlib=(-DZLIB_ROOT="$WORK/zlib")
    fi
    t=$(date +%s)
    mkdir -p "$BUILD"
    # pyngp then links the carried zlib's shared library: keep it beside pyngp (the build
    # that goes back includes it, and LD_LIBRARY_PATH names the folder).
    [ ${#zlib[@]} -eq 0 ] || cp -a "$WORK"/zlib/lib/libz.so* "$BUILD"/
    quiet cmake -S "$SRC" -B "$BUILD" -G Ninja "$COMPAT" -DCMAKE_BUILD_TYPE=Release \
        -DNGP_BUILD_WITH_GUI=OFF -DNGP_BUILD_WITH_OPTIX=OFF -DNGP_BUILD_WITH_VULKAN=OFF \
        -DTCNN_CUDA_ARCHITECTURES="$arch" -DPython_EXECUTABLE="$(command -v python3)" "${zlib[@]}" \
        || die "instant-ngp's configure failed (log.txt)"
    grep -q pyngp "$BUILD/build.ninja" \
        || note "no pyngp target: CMake found no Python development files; only the executable builds"
    quiet cmake --build "$BUILD" -j "$(nproc)" || die "instant-ngp's build failed (log.txt)"
    local secs=$(( $(date +%s) - t ))
    note "instant-ngp built in $secs s for sm_$arch"
    # Bring the build back in parts: the next lease skips the compile.
    (cd "$BUILD" && strip --strip-unneeded pyngp*.so instant-ngp 2>/dev/null;
     tar -cf - pyngp*.so instant-ngp $(ls libz.so* 2>/dev/null) | xz -T0 -6 > "$WORK/ingp-build.tar.xz")
    # A call returns at most 8 files of 16 MiB: the log, the JSON, the digest and 5 parts.
    if [ "$(stat -c %s "$WORK/ingp-build.tar.xz")" -le $((5 * PART)) ]; then
        split -b "$PART" -d -a 1 "$WORK/ingp-build.tar.xz" "$OUT/ingp-build.tar.xz.part"
    else
        note "the build ($(stat -c %s "$WORK/ingp-build.tar.xz") bytes of xz) is too large to come back in 5 parts"
    fi
    sha256sum "$WORK/ingp-build.tar.xz" | cut -d' ' -f1 > "$OUT/ingp-build.sha256"
    record build "{\"seconds\": $secs, \"arch\": \"$arch\", \"nvcc\": \"$(nvcc --version | tail -1)\",
        \"bytes_xz\": $(stat -c %s "$WORK/ingp-build.tar.xz"),
        \"parts\": $(ls "$OUT"/ingp-build.tar.xz.part* 2>/dev/null | wc -l)}"
}

# What a machine without CUDA can check of the carried source: the files instant-ngp's and
# tiny-cuda-nn's configure require, fmt, cmrc, pybind11 (against this python3's development
# files), zstr (against zlib, or the carried zlib built here), and one translation unit
# including every header-only dependency, compiled with the host compiler.
phase_check() {
    [ -f "$INGP/ingp-src.tar.xz" ] || die "$INGP/ingp-src.tar.xz: run scripts/ingp_pack.sh here first"
    rm -rf "$SRC" "$WORK/check"
    tar -C "$WORK" -xJf "$INGP/ingp-src.tar.xz" || die "unpacking instant-ngp failed"
    mkdir -p "$WORK/check"
    local zlib=()
    if [ ! -f /usr/include/zlib.h ] || [ -n "${FORCE_CARRIED_ZLIB:-}" ]; then
        quiet cmake -S "$SRC/dependencies/zlib" -B "$WORK/zlib-build" -G Ninja "$COMPAT" \
            -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$WORK/zlib" \
            && quiet cmake --build "$WORK/zlib-build" --target install \
            || die "building the carried zlib failed"
        zlib=(-DZLIB_ROOT="$WORK/zlib")
    fi
    cat > "$WORK/check/CMakeLists.txt" <<CMAKE
cmake_minimum_required(VERSION 3.18)
project(ingp_source_check C CXX)
set(S "$SRC")
set(T "\${S}/dependencies/tiny-cuda-nn")
foreach(f "\${S}/dependencies/glfw/CMakeLists.txt" "\${T}/dependencies/cutlass/CMakeLists.txt"
          "\${S}/configs/nerf/base.json" "\${S}/src/python_api.cu" "\${T}/src/fully_fused_mlp.cu")
  if(NOT EXISTS "\${f}")
    message(FATAL_ERROR "missing \${f}")
  endif()
endforeach()
set(FMT_UNICODE OFF CACHE BOOL "" FORCE)
add_subdirectory("\${T}/dependencies/fmt" fmt)
include("\${T}/dependencies/cmrc/CMakeRC.cmake")
cmrc_add_resource_library(check-resources NAMESPACE check)
find_package(Python 3.7 COMPONENTS Interpreter Development)
if(Python_FOUND)
  add_subdirectory("\${S}/dependencies/pybind11" pybind11)
  message(STATUS "check: pyngp would build against Python \${Python_VERSION}")
else()
  message(WARNING "check: no Python development files: pyngp would not build")
endif()
add_subdirectory("\${S}/dependencies/zstr" zstr)
add_executable(headers headers.cpp)
target_include_directories(headers PRIVATE "\${S}/dependencies" "\${S}/dependencies/tinylogger"
  "\${S}/dependencies/filesystem" "\${S}/dependencies/nanovdb" "\${S}/dependencies/NaturalSort"
  "\${T}/dependencies" "\${T}/dependencies/cutlass/include" "\${T}/include")
target_link_libraries(headers PRIVATE fmt zstr::zstr)
if(Python_FOUND)
  target_link_libraries(headers PRIVATE pybind11::embed)
  target_compile_definitions(headers PRIVATE WITH_PYBIND11)
endif()
CMAKE
    cat > "$WORK/check/headers.cpp" <<'CPP'
// The header-only dependencies instant-ngp's host code includes that need no CUDA, compiled once.
#include <args/args.hxx>
#include <filesystem/path.h>
#include <fmt/core.h>
#include <json/json.hpp>
#include <tinylogger/tinylogger.h>
#include <zstr.hpp>
#include <sstream>
#ifdef WITH_PYBIND11
#include <pybind11/embed.h>
#include <pybind11/numpy.h>
#endif
int main() {
    std::stringstream s;
    { zstr::ostream z(s); z << nlohmann::json{{"ok", fmt::format("{}", 1)}}.dump(); }
    zstr::istream back(s);
    std::string text;
    back >> text;
    tlog::info() << text;
    return text == "{\"ok\":\"1\"}" ? 0 : 1;
}
CPP
    quiet cmake -S "$WORK/check" -B "$WORK/check/build" -G Ninja "$COMPAT" -DCMAKE_BUILD_TYPE=Release \
        -DPython_EXECUTABLE="$(command -v python3)" "${zlib[@]}" \
        || die "the source check's configure failed (log.txt)"
    quiet cmake --build "$WORK/check/build" || die "the source check's build failed (log.txt)"
    quiet "$WORK/check/build/headers" || die "the source check's program failed"
    record check '{"configured": true, "built": true, "zstr_round_trip": true}'
}

phase_ingp() {
    setup_ours
    run "${DRIVER[@]}" train --scene "$LEGO/transforms_train.json" --minutes "$MINUTES" \
        --snapshots "$WORK/ingp_snapshots" > "$WORK/ingp_train.json" \
        || die "instant-ngp's training failed (log.txt)"
    record ingp_train "$WORK/ingp_train.json"
    local m
    for m in $(seq 1 "$MINUTES"); do
        run "${DRIVER[@]}" score --snapshot "$WORK/ingp_snapshots/ingp_${m}min.ingp" \
            --test "$LEGO/transforms_test.json" > "$WORK/ingp_score_$m.json" \
            && record "ingp_score_${m}min" "$WORK/ingp_score_$m.json"
    done
    # Ours opens instant-ngp's last snapshot here: nothing of this call outlives it.
    local last="$WORK/ingp_snapshots/ingp_${MINUTES}min.ingp"
    run "$BIN" eval --model "$last" --data "$LEGO" --device gpu --protocol instant-ngp \
        --no-lpips --json > "$WORK/ingp_by_us.json" && record ingp_by_us "$WORK/ingp_by_us.json"
}

phase_ours() {
    setup_ours
    local marks
    marks=$(seq -s, 1 "$MINUTES")
    run "$BIN" train "$LEGO" --device gpu --minutes "$MINUTES" --checkpoints "$marks" \
        --eval-views 8 --eval-protocol instant-ngp --out "$WORK/ours.ingp" --json \
        > "$WORK/ours_train.json" || die "our training failed (log.txt)"
    record ours_train "$WORK/ours_train.json"
}

phase_cross() {
    setup_ours
    [ -f "$WORK/ours.ingp" ] || phase_ours
    # The stego cover: lego with a hidden text, one minute.
    run "$BIN" synth --scene text --res 800 --train 100 --test 8 --out "$WORK/text" > /dev/null
    mkdir -p -m 700 "$WORK/keys"
    run "$BIN" keygen --out "$WORK/keys/text.key" > /dev/null
    run "$BIN" train "$LEGO" --hidden "$WORK/text" --key "$WORK/keys/text.key" --device gpu \
        --minutes 1 --out "$WORK/pair.ingp" --json > "$WORK/pair_train.json" \
        && record pair_train "$WORK/pair_train.json"
    local name
    for name in ours pair; do
        [ -f "$WORK/$name.ingp" ] || continue
        run "$BIN" eval --model "$WORK/$name.ingp" --data "$LEGO" --device gpu \
            --protocol instant-ngp --no-lpips --out "$WORK/${name}_views" --json \
            > "$WORK/${name}_eval.json" && record "${name}_eval_by_us" "$WORK/${name}_eval.json"
        run "${DRIVER[@]}" score --snapshot "$WORK/$name.ingp" --test "$LEGO/transforms_test.json" \
            --against "$WORK/${name}_views" > "$WORK/${name}_by_ingp.json" \
            && record "${name}_by_ingp" "$WORK/${name}_by_ingp.json"
    done
}

export REPO
export LD_LIBRARY_PATH=$BUILD${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
note "phases: $PHASES; minutes: $MINUTES"
command -v nvidia-smi > /dev/null \
    && nvidia-smi --query-gpu=name,driver_version,compute_cap --format=csv,noheader >> "$LOG" 2>&1
for p in $PHASES; do
    case $p in
        check|build|ingp|ours|cross) ;;
        *) die "unknown phase $p (check, build, ingp, ours, cross)" ;;
    esac
    case $p in ingp|cross) [ -d "$BUILD" ] || phase_build ;; esac
    note "phase $p"
    "phase_$p"
    record "${p}_done_at_seconds" "$(( $(date +%s) - T0 ))"
done
note "done"
