#!/usr/bin/env bash
# Download the cp312 manylinux x86_64 wheels that benchmarks/gpu.sh installs offline on the GPU machine.
#
#   bash benchmarks/gpu-wheels.sh        # -> benchmarks/wheels/ (carried) and benchmarks/wheels-dryrun/ (not)
#
# Versions: benchmarks/gpu-requirements.txt, section [carried] into benchmarks/wheels/ (carry it with the device
# tool: `carry: ["benchmarks/wheels"]`, 64 MiB limit for the whole working tree), section [image] (packages the GPU
# image already has) into benchmarks/wheels-dryrun/ for the CPU dry run's fresh Python 3.12 check. Both folders are
# ignored by git. Needs pip and a package index; the wheels are platform wheels, any host Python can fetch them.
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
REQ="$HERE/gpu-requirements.txt"
PIP="${PIP:-$(command -v python3) -m pip}"
PYVER="${PYVER:-3.12}"  # the GPU image's Python (2026-11: 3.12.3); benchmarks/gpu.sh reads the same variable
section() {  # the pins of one section of $REQ, one per line
  awk -v want="[$1]" '/^# \[/ {on = ($2 == want); next} on && $0 !~ /^#/ && NF {print $1}' "$REQ"
}
fetch() {  # fetch DEST SECTION
  local dest="$1" names
  mapfile -t names < <(section "$2")
  [ "${#names[@]}" -gt 0 ] || { echo "no pins in section [$2] of $REQ" >&2; exit 1; }
  mkdir -p "$dest"
  # --no-deps: every needed wheel is pinned in $REQ (one version each: two would stop the offline install)
  $PIP download --quiet --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
    --abi "cp${PYVER/./}" \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --abi abi3 --abi none \
    -d "$dest" "${names[@]}"
  # Only the pinned files stay (an earlier pin's wheel would make two versions)
  local keep=() f n
  for n in "${names[@]}"; do keep+=("$(echo "${n%%==*}" | tr 'A-Z_.' 'a-z--')-${n##*==}"); done
  for f in "$dest"/*.whl; do
    n="$(basename "$f" | awk -F- '{print $1"-"$2}' | tr 'A-Z_.' 'a-z--')"
    local ok=0 k
    for k in "${keep[@]}"; do [ "$n" = "$(echo "$k" | tr '.' '-')" ] && ok=1; done
    [ "$ok" = 1 ] || { echo "removing stale $(basename "$f")"; rm -f "$f"; }
  done
  echo "$dest: $(ls "$dest"/*.whl | wc -l) wheels, $(du -sh "$dest" | cut -f1)"
}
fetch "$HERE/wheels" carried
fetch "$HERE/wheels-dryrun" image
