#!/usr/bin/env bash
# Packs instant-ngp's source, with only what a headless build needs of its submodules, into
# one tarball that scripts/ingp_lease.sh unpacks and builds on a lent GPU machine (which has
# no network), and says whether it fits in the 64 MiB a call may carry beside the
# repository and scripts/gpu_bench.py's carry (our binary, lego, the Vulkan loader).
#
#   scripts/ingp_pack.sh [OUT_DIR] [BENCH_CARRY]
#
# OUT_DIR (default .carry-ingp) receives ingp-src.tar.xz and ingp-src.json (every commit and
# path packed, and the sizes). BENCH_CARRY (default .carry) is gpu_bench.py's folder, counted
# in the total when it exists. Sources come from git directories, never from the network:
#   INGP_MIRROR  a folder of bare mirrors named OWNER+NAME/repo (default /work/.mirror, what
#                this workplace's fetch tool writes), or
#   INGP_CLONE   a `git clone --recursive` of NVlabs/instant-ngp (its .git/modules are read).
# Each submodule is taken at the commit instant-ngp's tree pins (tiny-cuda-nn's own
# submodules at the commits its tree pins), except glfw, whose CMakeLists.txt alone is packed
# from any commit: instant-ngp's configure stops unless that file exists, even with the GUI
# off, and reads nothing else of glfw then.
#
# What a headless build (NGP_BUILD_WITH_GUI=OFF, OPTIX=OFF, VULKAN=OFF; Python bindings on)
# compiles or includes, read from the two CMakeLists.txt and the #includes:
#   instant-ngp: CMakeLists.txt cmake/ configs/nerf/ include/ src/ and the in-tree
#     dependencies filesystem, NaturalSort, nanovdb, stb_image, tinyexr, tinyobjloader,
#     pybind11_json
#   tiny-cuda-nn: CMakeLists.txt include/ src/ dependencies/{json,pcg32,stbi}, and its
#     submodules fmt (add_subdirectory; its target lists README.rst and ChangeLog.rst as
#     sources, so they must be there), cmrc (CMakeRC.cmake, the RTC headers) and cutlass
#     (include/ and tools/util/include/ for cutlass_mlp.cu; CMakeLists.txt for the check)
#   pybind11 (pyngp, which scripts/ingp_driver.py drives), zstr (snapshots; it needs zlib),
#   tinylogger, args (the instant-ngp executable), and zlib's source, built on the machine
#   only when it has no zlib.h.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/.." && pwd)
OUT=${1:-$REPO/.carry-ingp}
BENCH=${2:-$REPO/.carry}
MIRROR=${INGP_MIRROR:-/work/.mirror}
CLONE=${INGP_CLONE:-}
INGP_COMMIT=${INGP_COMMIT:-}
LIMIT=$((64 * 1024 * 1024))

die() { echo "ingp_pack: error: $*" >&2; exit 1; }

# The git directory holding repository OWNER/NAME (for a submodule at PATH of instant-ngp).
gitdir_for() {
    local slug=$1 sub=${2:-}
    local d="$MIRROR/${slug/\//+}/repo"
    if [ -d "$d" ]; then echo "$d"; return; fi
    if [ -n "$CLONE" ]; then
        if [ -z "$sub" ]; then echo "$CLONE/.git"; return; fi
        if [ -d "$CLONE/.git/modules/$sub" ]; then echo "$CLONE/.git/modules/$sub"; return; fi
    fi
    die "no git directory for $slug (fetch it into $MIRROR/${slug/\//+}/repo, or set INGP_CLONE)"
}

# The commit a parent tree pins for its submodule at PATH.
pinned() {
    local gd=$1 commit=$2 path=$3
    git --git-dir="$gd" ls-tree "$commit" "$path" | awk '$2 == "commit" { print $3 }'
}

MANIFEST=()
# Writes PATHS of COMMIT in GITDIR under DEST, reading only those paths' blobs (a mirror may
# lack the large files elsewhere in the tree, which `git archive` would stop on).
export_paths() {
    local gd=$1 commit=$2 dest=$3; shift 3
    git --git-dir="$gd" cat-file -e "$commit^{commit}" 2>/dev/null \
        || die "$gd has no commit $commit"
    local idx; idx=$(mktemp)
    GIT_INDEX_FILE=$idx git --git-dir="$gd" read-tree "$commit"
    mkdir -p "$dest"
    local n
    n=$(GIT_INDEX_FILE=$idx git --git-dir="$gd" ls-files -z -- "$@" | tr -cd '\0' | wc -c)
    [ "$n" -gt 0 ] || die "$gd@$commit: none of $* exists"
    GIT_INDEX_FILE=$idx git --git-dir="$gd" ls-files -z -- "$@" \
        | GIT_INDEX_FILE=$idx xargs -0 git --git-dir="$gd" checkout-index --prefix="$dest/" --
    rm -f "$idx"
    MANIFEST+=("{\"dest\": \"${dest#"$STAGE"/}\", \"commit\": \"$commit\", \"files\": $n, \"paths\": \"$*\"}")
}

STAGE=$(mktemp -d)
trap 'rm -rf "$STAGE"' EXIT
SRC=$STAGE/instant-ngp

NGP=$(gitdir_for NVlabs/instant-ngp)
[ -n "$INGP_COMMIT" ] || INGP_COMMIT=$(git --git-dir="$NGP" rev-parse HEAD)
export_paths "$NGP" "$INGP_COMMIT" "$SRC" CMakeLists.txt LICENSE.txt cmake configs/nerf \
    include src dependencies/filesystem dependencies/NaturalSort dependencies/nanovdb \
    dependencies/stb_image dependencies/tinyexr dependencies/tinyobjloader \
    dependencies/pybind11_json

TCNN_C=$(pinned "$NGP" "$INGP_COMMIT" dependencies/tiny-cuda-nn)
TCNN=$(gitdir_for NVlabs/tiny-cuda-nn dependencies/tiny-cuda-nn)
TD=$SRC/dependencies/tiny-cuda-nn
export_paths "$TCNN" "$TCNN_C" "$TD" CMakeLists.txt LICENSE.txt include src \
    dependencies/json dependencies/pcg32 dependencies/stbi
export_paths "$(gitdir_for fmtlib/fmt dependencies/tiny-cuda-nn/modules/dependencies/fmt)" \
    "$(pinned "$TCNN" "$TCNN_C" dependencies/fmt)" "$TD/dependencies/fmt" \
    CMakeLists.txt LICENSE.rst README.rst ChangeLog.rst include src support/cmake
export_paths "$(gitdir_for vector-of-bool/cmrc dependencies/tiny-cuda-nn/modules/dependencies/cmrc)" \
    "$(pinned "$TCNN" "$TCNN_C" dependencies/cmrc)" "$TD/dependencies/cmrc" \
    CMakeLists.txt CMakeRC.cmake LICENSE.txt
export_paths "$(gitdir_for NVIDIA/cutlass dependencies/tiny-cuda-nn/modules/dependencies/cutlass)" \
    "$(pinned "$TCNN" "$TCNN_C" dependencies/cutlass)" "$TD/dependencies/cutlass" \
    CMakeLists.txt LICENSE.txt include tools/util/include

for spec in "pybind/pybind11 dependencies/pybind11 CMakeLists.txt LICENSE include tools" \
            "Tom94/zstr dependencies/zstr CMakeLists.txt LICENSE src" \
            "Tom94/tinylogger dependencies/tinylogger LICENSE.md tinylogger" \
            "Taywee/args dependencies/args LICENSE args.hxx" \
            "Tom94/zlib dependencies/zlib"; do
    set -- $spec
    slug=$1 path=$2; shift 2
    # instant-ngp's .gitmodules names a fork (Tom94/pybind11) whose mirror may lack the
    # pinned commit; upstream pybind11 holds it.
    [ $# -gt 0 ] || set -- .
    export_paths "$(gitdir_for "$slug" "$path")" "$(pinned "$NGP" "$INGP_COMMIT" "$path")" \
        "$SRC/$path" "$@"
done
# zlib's contributed code (only its optional assembly is referenced), docs and old ports
# are not needed to build it; its CMakeLists.txt lists win32/zlib1.rc and installs zlib.3.
rm -rf "$SRC"/dependencies/zlib/{contrib,doc,examples,amiga,msdos,nintendods,old,os400,qnx,watcom,zlib.3.pdf}

GLFW=$(gitdir_for Tom94/glfw dependencies/glfw)
GLFW_PIN=$(pinned "$NGP" "$INGP_COMMIT" dependencies/glfw)
if git --git-dir="$GLFW" cat-file -e "$GLFW_PIN^{commit}" 2>/dev/null; then GLFW_C=$GLFW_PIN
else GLFW_C=$(git --git-dir="$GLFW" rev-parse HEAD); fi
export_paths "$GLFW" "$GLFW_C" "$SRC/dependencies/glfw" CMakeLists.txt LICENSE.md

mkdir -p "$OUT"
RAW=$(du -sb "$SRC" | cut -f1)
# xz -9e: the tarball travels on every call; unpacking it costs a second there.
tar -C "$STAGE" --sort=name --owner=0 --group=0 --numeric-owner --mtime=@0 -cf - instant-ngp \
    | xz -9e -T0 > "$OUT/ingp-src.tar.xz.tmp"
mv "$OUT/ingp-src.tar.xz.tmp" "$OUT/ingp-src.tar.xz"
TAR=$(stat -c %s "$OUT/ingp-src.tar.xz")

# What a call carries: the repository's tracked and untracked-not-ignored files, this
# folder, and gpu_bench.py's carry.
TRACKED=$(cd "$REPO" && git ls-files -z --cached --others --exclude-standard \
    | xargs -0 stat -c %s 2>/dev/null | awk '{s += $1} END {print s + 0}')
OURS=$(du -sb "$OUT" | cut -f1)
BENCH_BYTES=0
[ -d "$BENCH" ] && BENCH_BYTES=$(du -sb "$BENCH" | cut -f1)
TOTAL=$((TRACKED + OURS + BENCH_BYTES))

{
    echo "{"
    echo " \"instant_ngp\": \"$INGP_COMMIT\","
    echo " \"glfw_cmakelists_from\": \"$GLFW_C\", \"glfw_pinned\": \"$GLFW_PIN\","
    echo " \"source_bytes\": $RAW, \"tar_xz_bytes\": $TAR,"
    echo " \"repository_bytes\": $TRACKED, \"bench_carry_bytes\": $BENCH_BYTES,"
    echo " \"total_bytes\": $TOTAL, \"limit_bytes\": $LIMIT,"
    echo " \"packed\": ["
    printf '  %s' "${MANIFEST[0]}"
    printf ',\n  %s' "${MANIFEST[@]:1}"
    printf '\n ]\n}\n'
} > "$OUT/ingp-src.json"
cat "$OUT/ingp-src.json"
mib() { awk -v b="$1" 'BEGIN { printf "%.1f", b / 1048576 }'; }
echo "ingp_pack: source $(mib "$RAW") MiB -> $(mib "$TAR") MiB xz; with the repository" \
     "($(mib "$TRACKED")) and $BENCH ($(mib "$BENCH_BYTES")): $(mib "$TOTAL") MiB of 64" >&2
if [ "$TOTAL" -gt "$LIMIT" ]; then
    die "$TOTAL bytes: past the 64 MiB a call may carry"
fi
