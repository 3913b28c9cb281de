#!/usr/bin/env bash
# Everything the GPU machine is for, in one command (< 8 min on one H200): one JSON and the logs under $OUT.
#
#   bash benchmarks/gpu.sh                  # on the GPU machine (device tool: carry benchmarks/wheels)
#   bash benchmarks/gpu.sh --dry-run        # the same steps on CPU at tiny sizes (~2 min); = DEVICE=cpu
#   bash benchmarks/gpu.sh --experiment     # also step (d), a grid of GPU learners (+~2 min)
#
# Steps (docs/PERFORMANCE.md, "GPU"):
#   0. a venv over the machine's Python (its CUDA torch is reused, never another torch installed), the carried
#      cp312 wheels (benchmarks/wheels: mujoco, gymnasium, eclipse-zenoh and their needs) installed offline, the
#      project with --no-deps; a check that the wheels import and work (HalfCheetah-v5 steps, a Zenoh session).
#   a. mam bench --only learner: K = 1, 2 against the reference TD3, interleaved; the update through CUDA graphs
#      (the default on a GPU, mam_core/graphs.py) and launched op by op (`k<K>_eager`); a mini-batch per actor
#      and --shared-batch; fp32 and bf16; SAC; the device's busy time per update (torch.profiler).
#   b. graphs-check: the graphed update against the eager one over 100 updates (MA-TD3 and MA-SAC, the
#      elimination half-way), and two run_reference runs of one seed on the GPU: equal policy bits?
#   c. mam run --env HalfCheetah-v5 --algo ma-td3 (K=2, --schedule paper) for E2E_SECONDS of training after its
#      random phase, then stopped, for each of E2E_RUNS (M workers, lag B, graphs on/off): env steps/s, updates/s,
#      the learner's wait share from its learner.jsonl; nvidia-smi utilization.
#   d. (--experiment) mam experiment --parallel 8 of GPU learners for at most EXPERIMENT_SECONDS.
# Output: $OUT/gpu.json (every figure), $OUT/gpu.log (this script's transcript), $OUT/logs.tar.gz (each step's
# log and JSON, the runs' learner.jsonl): 3 files, within the device tool's 8-file limit.
#
# Environment: OUT (default ./gpu-out), DEVICE (cuda; cpu = --dry-run), PYTHON (the base Python; default
# python3 on a GPU; for the dry run a python3.12 with torch, else the project's .venv), WORK (scratch: venvs,
# run dirs; default a new folder under /tmp, removed at the end unless KEEP_WORK=1), E2E_SECONDS, E2E_RUNS
# ("TAG:M:LAG[:nographs] ..."), EXPERIMENT_SECONDS, PARALLEL.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
DRY=0; EXPERIMENT=0
for arg in "$@"; do
  case "$arg" in
    --dry-run) DRY=1 ;;
    --experiment) EXPERIMENT=1 ;;
    --no-experiment) EXPERIMENT=0 ;;
    -h|--help) sed -n '2,/^set -uo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "unknown argument $arg (see --help)" >&2; exit 2 ;;
  esac
done
DEVICE="${DEVICE:-cuda}"
[ "$DRY" = 1 ] && DEVICE=cpu
[ "$DEVICE" = cpu ] && DRY=1
OUT="${OUT:-$ROOT/gpu-out}"
mkdir -p "$OUT"
OUT="$(cd "$OUT" && pwd)"
OWN_WORK=0
[ -z "${WORK:-}" ] && OWN_WORK=1 && WORK="$(mktemp -d /tmp/mam-gpu.XXXXXX)"
mkdir -p "$WORK/logs"
LOGS="$WORK/logs"
exec > >(tee "$OUT/gpu.log") 2>&1
export PYTHONUNBUFFERED=1
T_START=$(date +%s)
declare -A T
FAILED=()
say() { echo "[gpu.sh $(( $(date +%s) - T_START ))s] $*"; }
die() { say "FAILED: $*"; finish; exit 1; }
timed() {  # timed NAME LIMIT_S CMD...: run with a time limit, log to $LOGS/NAME.log, seconds into T[NAME]
  local name="$1" limit="$2" t0 rc; shift 2
  t0=$(date +%s)
  say "$name: $*"
  timeout --signal=TERM --kill-after=30 "$limit" "$@" >"$LOGS/$name.log" 2>&1; rc=$?
  T[$name]=$(( $(date +%s) - t0 ))
  say "$name: exit $rc after ${T[$name]} s"
  [ "$rc" = 0 ] || { FAILED+=("$name"); tail -n 25 "$LOGS/$name.log"; }
  return "$rc"
}
finish() {  # the one JSON (from whatever steps ran) and the logs
  local timings="{" k
  for k in "${!T[@]}"; do timings+="\"$k\": ${T[$k]}, "; done
  local failed=""
  [ "${#FAILED[@]}" -gt 0 ] && failed="$(printf '"%s",' "${FAILED[@]}")"
  timings+="\"failed_steps\": [${failed%,}], "
  timings+="\"total\": $(( $(date +%s) - T_START ))}"
  echo "$timings" >"$LOGS/timings.json"
  local py="${VPY:-${BASE_PY:-python3}}"
  [ -x "$py" ] || command -v "$py" >/dev/null || py=python3
  "$py" benchmarks/gpu_steps.py combine --device "$DEVICE" $([ "$DRY" = 1 ] && echo --dry-run) \
    --bench "$LOGS/bench.json" --graphs-check "$LOGS/graphs_check.json" --e2e "$LOGS"/e2e-*.json \
    --experiment "$LOGS/experiment.json" --wheels "$LOGS/wheels_check.json" --setup "$LOGS/setup.json" \
    --timings "$LOGS/timings.json" --out "$OUT/gpu.json" || say "combine failed"
  for f in "$WORK"/e2e-*/learner.jsonl; do
    [ -f "$f" ] && cp "$f" "$LOGS/$(basename "$(dirname "$f")").learner.jsonl"
  done
  cp "$WORK"/*.log "$LOGS/" 2>/dev/null
  tar -czf "$OUT/logs.tar.gz" -C "$WORK" logs
  [ "$OWN_WORK" = 1 ] && [ -z "${KEEP_WORK:-}" ] && rm -rf "$WORK"  # venvs and run dirs (KEEP_WORK=1 keeps them)
  say "wrote $OUT/gpu.json, $OUT/gpu.log, $OUT/logs.tar.gz (total $(( $(date +%s) - T_START )) s)"
}

# Sizes: the GPU's, or tiny ones for the dry run (seconds, meaningless figures).
if [ "$DRY" = 1 ]; then
  BENCH_SIZES=(--rounds 2 --updates 3 --hidden 32,32 --batch-size 32)
  CHECK_SIZES=(--hidden 32,32 --batch-size 32 --updates 10 --steps 300 --start-steps 100 --compete-every 100)
  RUN_SIZES=(--hidden 32,32 --batch-size 32 --start-steps 300 --compete-every 1000 --eval-episodes 1 --grace 30)
  E2E_SECONDS="${E2E_SECONDS:-8}"; EXPERIMENT_SECONDS="${EXPERIMENT_SECONDS:-45}"
  E2E_RUNS="${E2E_RUNS:-m2-lag0:2:0 m2-lag2:2:2}"
  PARALLEL="${PARALLEL:-2}"; GRID=(--algos td3 --seeds 2 --steps 1000)
else
  BENCH_SIZES=(--rounds 5 --updates 100 --hidden 256,256 --batch-size 256)
  CHECK_SIZES=(--hidden 256,256 --batch-size 256 --updates 100 --steps 1500 --start-steps 500 --compete-every 500)
  # paper schedule (iterations): start 1000 instead of Table 3's 25,000 so the window is spent training
  RUN_SIZES=(--hidden 256,256 --batch-size 256 --start-steps 1000 --compete-every 5000 --eval-episodes 20)
  E2E_SECONDS="${E2E_SECONDS:-30}"
  E2E_RUNS="${E2E_RUNS:-m3-lag0:3:0 m3-lag2:3:2 m3-lag2-eager:3:2:nographs m8-lag2:8:2 m16-lag2:16:2}"
  EXPERIMENT_SECONDS="${EXPERIMENT_SECONDS:-60}"
  PARALLEL="${PARALLEL:-8}"; GRID=(--algos ma-td3,td3 --seeds 4 --steps 20000)
fi
say "device $DEVICE, dry run $DRY, out $OUT, work $WORK"

# ---------------------------------------------------------------- 0. the environment
py312() {  # a Python 3.12 on this machine, or nothing
  local p
  for p in "$(command -v python3.12 2>/dev/null)" /usr/bin/python3.12 "$HOME"/.pyenv/versions/3.12*/bin/python3.12; do
    [ -n "$p" ] && [ -x "$p" ] && "$p" -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null \
      && { echo "$p"; return; }
  done
}
WHEELS="$ROOT/benchmarks/wheels"
DRY_WHEELS="$ROOT/benchmarks/wheels-dryrun"
if [ "$DRY" = 1 ] && { [ ! -d "$WHEELS" ] || [ ! -d "$DRY_WHEELS" ]; }; then
  timed wheels_download 300 bash benchmarks/gpu-wheels.sh \
    || { unset 'FAILED[-1]'; say "no wheels (no package index?): the wheels check is skipped"; }
fi
if [ -n "${PYTHON:-}" ]; then
  BASE_PY="$PYTHON"
elif [ "$DRY" = 0 ]; then
  BASE_PY=python3
else
  BASE_PY=""
  P312="$(py312)"
  [ -n "$P312" ] && "$P312" -c 'import torch' 2>/dev/null && BASE_PY="$P312"
  [ -z "$BASE_PY" ] && BASE_PY="$ROOT/.venv/bin/python"  # no Python 3.12 with torch here: the project's venv
fi
command -v "$BASE_PY" >/dev/null || die "no base Python $BASE_PY"
"$BASE_PY" -c 'import torch' 2>/dev/null || die "$BASE_PY has no torch (the script never installs one)"
if [ "$DEVICE" = cuda ]; then
  "$BASE_PY" -c 'import torch; assert torch.cuda.is_available()' || die "$BASE_PY's torch sees no CUDA device"
  nvidia-smi >"$LOGS/nvidia-smi.txt" 2>&1
fi
VENV="$WORK/venv"
# Venvs without pip of their own: the base Python's pip installs into them (pip --python), which is quicker
# than ensurepip and, on Python <= 3.11, keeps the bundled setuptools 65 (no bdist_wheel) out of them.
"$BASE_PY" -m pip --version >/dev/null 2>&1 || die "$BASE_PY has no pip"
make_venv() {  # make_venv DIR BASE_PYTHON LINK(1: see the base Python's packages, 0: nothing but its stdlib)
  local dir="$1" base="$2" site
  if [ "$3" = 1 ] && "$base" -c 'import sys; sys.exit(sys.prefix == sys.base_prefix)'; then
    # The base Python is itself a venv (the GPU image's /opt/torch/.venv, the project's .venv): there
    # --system-site-packages would show the base *interpreter's* packages, not the venv's (its torch), and put
    # them first. So a plain venv, then the base's site directories in the base's own order, after this venv's
    # own (what is installed here wins), with their .pth files.
    "$base" -m venv --without-pip "$dir" || return 1
    site="$("$dir/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
    "$base" -c 'import sys
for p in sys.path:
    if p.rstrip("/").endswith(("site-packages", "dist-packages")):
        print(f"import site; site.addsitedir({p!r})")' >"$site/_mam_base_python.pth"
  elif [ "$3" = 1 ]; then
    "$base" -m venv --without-pip --system-site-packages "$dir"
  else
    "$base" -m venv --without-pip "$dir"
  fi
}
pyver() { "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])'; }
T0=$(date +%s)
make_venv "$VENV" "$BASE_PY" 1 || die "venv over $BASE_PY"
VPY="$VENV/bin/python"
PIP=("$BASE_PY" -m pip --python "$VPY" install --quiet --no-index --no-deps --no-cache-dir --no-compile
     --disable-pip-version-check --ignore-installed)
WHEELS_INSTALLED=0
PYVER="${PYVER:-3.12}"  # the Python the carried wheels are for (benchmarks/gpu-wheels.sh)
if [ "$(pyver "$VPY")" = "$PYVER" ] && compgen -G "$WHEELS/*.whl" >/dev/null; then
  "${PIP[@]}" "$WHEELS"/*.whl >"$LOGS/pip_wheels.log" 2>&1 || die "offline install of $WHEELS (see logs)"
  WHEELS_INSTALLED=1
else
  say "carried wheels not installed into the venv: Python $(pyver "$VPY") (the base's own mujoco/gymnasium/zenoh)"
fi
if ! "${PIP[@]}" --no-build-isolation -e "$ROOT" >"$LOGS/pip_project.log" 2>&1; then
  say "pip install -e . failed (see logs): the project goes on the venv's path instead"
  echo "$ROOT" >"$("$VPY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/_mam_project.pth"
  printf '#!/bin/sh\nexec "%s" -m services.cli "$@"\n' "$VPY" >"$VENV/bin/mam"; chmod +x "$VENV/bin/mam"
fi
T[setup]=$(( $(date +%s) - T0 ))
"$VPY" - "$LOGS/setup.json" "$BASE_PY" "$WHEELS_INSTALLED" <<'EOF' || die "the venv does not import the project"
import importlib.metadata as md, json, sys, torch, mam_core.agent, services.cli.app  # noqa: E401
def version(d):
    try:
        return md.version(d)
    except md.PackageNotFoundError:
        return None
names = ("mujoco", "gymnasium", "eclipse-zenoh", "numpy", "typer", "click", "rich", "msgpack", "tensorboard",
         "matplotlib", "imageio")
out = {"base_python": sys.argv[2], "venv_python": sys.version.split()[0], "torch": torch.__version__,
       "torch_file": torch.__file__, "cuda_available": torch.cuda.is_available(), "carried_wheels_installed":
       sys.argv[3] == "1", "packages": {d: version(d) for d in names}}
out["package_files"] = {m: __import__(m).__file__ for m in ("mujoco", "gymnasium", "zenoh")}
json.dump(out, open(sys.argv[1], "w"), indent=1)
EOF
say "venv ready in ${T[setup]} s: $(cat "$LOGS/setup.json" | tr -d '\n' | cut -c1-300)"

# The wheels work: in the venv on the GPU; on the dry run in a fresh Python 3.12 venv that has nothing else.
if [ "$DRY" = 0 ] || [ "$WHEELS_INSTALLED" = 1 ]; then
  timed wheels_check 120 "$VPY" benchmarks/gpu_steps.py wheels-check --out "$LOGS/wheels_check.json"
elif [ -n "$(py312)" ] && compgen -G "$WHEELS/*.whl" >/dev/null && compgen -G "$DRY_WHEELS/*.whl" >/dev/null; then
  T0=$(date +%s)
  if make_venv "$WORK/venv312" "$(py312)" 0 && "$BASE_PY" -m pip --python "$WORK/venv312/bin/python" install \
      --quiet --no-index --no-deps --no-cache-dir --no-compile --disable-pip-version-check \
      "$WHEELS"/*.whl "$DRY_WHEELS"/*.whl \
      >"$LOGS/pip_wheels312.log" 2>&1; then
    T[venv312]=$(( $(date +%s) - T0 ))
    "$BASE_PY" -m pip --python "$WORK/venv312/bin/python" check >"$LOGS/pip_check312.log" 2>&1 \
      || { FAILED+=(pip_check312); say "pip check in the Python 3.12 venv: $(cat "$LOGS/pip_check312.log")"; }
    timed wheels_check 120 "$WORK/venv312/bin/python" benchmarks/gpu_steps.py wheels-check \
      --out "$LOGS/wheels_check.json"
  else
    FAILED+=(venv312); say "the fresh Python 3.12 venv could not install the wheels (see logs)"
  fi
else
  say "no Python 3.12 or no wheels here: the wheels check is skipped"
fi

# ---------------------------------------------------------------- a. the learner bench
timed bench 300 "$VENV/bin/mam" bench --device "$DEVICE" --only learner --ks 1,2 --variants default --device-time \
  --shapes halfcheetah --threads 1 "${BENCH_SIZES[@]}" --out "$LOGS/bench.json"

# ---------------------------------------------------------------- b. graphed == eager; one seed, one run
timed graphs_check 240 "$VPY" benchmarks/gpu_steps.py graphs-check --device "$DEVICE" "${CHECK_SIZES[@]}" \
  --out "$LOGS/graphs_check.json"

# ---------------------------------------------------------------- c. mam run, time-boxed, per configuration
for spec in $E2E_RUNS; do
  IFS=: read -r tag workers lag graphs <<<"$spec"
  extra=(); [ "${graphs:-}" = nographs ] && extra=(--no-graphs)
  timed "e2e-$tag" $(( E2E_SECONDS + 200 )) "$VPY" benchmarks/gpu_steps.py e2e --device "$DEVICE" \
    --seconds "$E2E_SECONDS" --work "$WORK" --workers "$workers" --lag "$lag" --tag "$tag" "${extra[@]}" \
    "${RUN_SIZES[@]}" --out "$LOGS/e2e-$tag.json"
done

# ---------------------------------------------------------------- d. a grid of GPU learners, time-boxed
if [ "$EXPERIMENT" = 1 ]; then
  timed experiment $(( EXPERIMENT_SECONDS + 120 )) "$VPY" benchmarks/gpu_steps.py experiment --device "$DEVICE" \
    --parallel "$PARALLEL" --seconds "$EXPERIMENT_SECONDS" --work "$WORK" "${RUN_SIZES[@]}" "${GRID[@]}" \
    --out "$LOGS/experiment.json"
fi
finish
"$BASE_PY" - "$OUT/gpu.json" <<'EOF'
import json, sys
d = json.load(open(sys.argv[1]))
print(json.dumps({"device": d["device"], "dry_run": d["dry_run"], **d["derived"], "goals": d["goals"],
                  "timings_s": d["timings_s"]}, indent=1, default=str))
EOF
[ "${#FAILED[@]}" = 0 ] || { say "failed steps: ${FAILED[*]}"; sleep 1; exit 1; }
sleep 1  # tee writes the last lines of gpu.log
