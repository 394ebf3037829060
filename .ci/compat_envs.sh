#!/usr/bin/env bash
# The declared floors, tested (docs/compatibility.md): after `make test` (the pinned torch), the core and
# framework-integration tests on the floor torch and on the newest torch on the registry, and the core
# blocks' forward and backward (+ import) on every Python version pyproject.toml declares.
# Each environment is a venv under $COMPAT_DIR, reused while its package list (stamp) is unchanged: they
# hold only third-party packages (the library is taken from src/ via PYTHONPATH), so the default lies in
# the user's cache, shared by every clone: only the first run installs (about 19 GB; docs/compatibility.md).
# Prints one line of test counts per environment and fails when any environment has a failure.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
COMPAT_DIR=${COMPAT_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/mssf-blocks/compat-envs}
# this machine's pip config caps torch (/etc/xdg/pip/constraints.txt); the newest release lies above it
export PIP_CONSTRAINT=/dev/null PIP_DISABLE_PIP_VERSION_CHECK=1
export OMP_NUM_THREADS=1 PYTHONPATH="$ROOT/src" PYTHONDONTWRITEBYTECODE=1

FLOOR_TORCH="torch==2.1.2"   # the newest torch with mmcv 2.1.0 wheels (mmdetection3d 1.4): pyproject's floor
NEWEST_TORCH="torch"         # whatever is newest on the registry (CUDA builds: they run on the CPU)
# the core and framework-integration tests (everything but the example detectors, docs and packaging)
CORE_TESTS=(tests/functional tests/integrations tests/checks/test_audit_inputs.py tests/blocks/test_fusion_block.py
            tests/integrations/test_spconv.py tests/test_torch_versions.py tests/test_compile.py tests/diagnostics/test_diagnostics.py
            tests/test_export.py
            tests/samplers/test_sff.py tests/geometry/test_voxel_centroid_projector.py tests/heads/test_semantic_guided_head.py tests/lift/test_pillar_lift.py tests/samplers/test_msdff.py
            tests/weights/test_authors_forward.py tests/samplers/test_precision.py tests/test_sparse_voxels.py tests/test_static_path.py
            tests/test_testing.py tests/test_voxel_grid.py tests/blocks/test_fusion_block_grid.py
            tests/samplers/test_sff_tester.py tests/samplers/test_msdff_tester.py tests/geometry/test_voxel_centroid_projector_tester.py
            tests/heads/test_semantic_guided_head_tester.py tests/lift/test_pillar_lift_tester.py tests/blocks/test_fusion_block_tester.py)
# per Python version: import + forward / backward / gradcheck of the core blocks
PY_TESTS=(tests/test_torch_versions.py tests/samplers/test_sff.py tests/samplers/test_msdff.py tests/lift/test_pillar_lift.py tests/heads/test_semantic_guided_head.py
          tests/geometry/test_voxel_centroid_projector.py tests/test_voxel_grid.py
          tests/samplers/test_sff_tester.py tests/samplers/test_msdff_tester.py tests/heads/test_semantic_guided_head_tester.py)
TEST_DEPS=(einops pytest hypothesis)
FRAMEWORK_DEPS=(shapely pyyaml easydict "spconv>=2.3" tqdm pillow addict yapf termcolor rich)
# what OpenPCDet's code (tests/integrations, the archive in ../shared) imports at module level, as the Makefile
# installs it (av2 and kornia --no-deps below), and the optional packages of a few core tests (ONNX, plots)
OPENPCDET_DEPS=(scipy scikit-image SharedArray pyquaternion tensorboardX numba pandas universal_pathlib)
OPTIONAL_DEPS=(onnx onnxruntime onnxscript matplotlib)

find_python() {  # python3.X on PATH, else pyenv's
  local v=$1 p
  if p=$(command -v "python$v") && "$p" -c "" 2>/dev/null; then echo "$p"; return; fi
  for p in "$(pyenv root 2>/dev/null || echo "$HOME/.pyenv")"/versions/"$v".*/bin/python"$v"; do
    [ -x "$p" ] && { echo "$p"; return; }
  done
  echo "compat_envs: no python$v on PATH or in pyenv" >&2; return 1
}

TORCH_PURE_DEPS=(filelock fsspec jinja2 networkx sympy typing-extensions setuptools)
version_of() { "$1/bin/python" -c 'import torch, sys; print(f"torch {torch.__version__}, Python {sys.version.split()[0]}")'; }

# make_torch_env NAME TORCH_SPEC NUMPY_SPEC: Python 3.11, the torch, the test and framework dependencies
make_torch_env() {
  local name=$1 torch_spec=$2 numpy_spec=$3 env=$COMPAT_DIR/$1 t0=$SECONDS
  # with numpy 1 (the floor), the last releases built for it: opencv < 4.11; pyarrow 24+ requires numpy 2
  # (23.0.1 tested)
  local pins=(pyarrow opencv-python-headless)
  [ "$numpy_spec" != "numpy<2" ] || pins=("pyarrow<24" "opencv-python-headless<4.11")
  local stamp="3.11 $torch_spec $numpy_spec ${pins[*]} ${TEST_DEPS[*]} ${FRAMEWORK_DEPS[*]} ${OPENPCDET_DEPS[*]} ${OPTIONAL_DEPS[*]} vod-tudelft"
  [ -f "$env/.stamp" ] && [ "$(cat "$env/.stamp")" = "$stamp" ] && { echo "  $name: reused ($(version_of "$env"))"; return; }
  rm -rf "$env" && "$(find_python 3.11)" -m venv "$env"
  "$env/bin/pip" install --quiet "$torch_spec" "$numpy_spec" "${TEST_DEPS[@]}" "${FRAMEWORK_DEPS[@]}" \
    "${OPENPCDET_DEPS[@]}" "${pins[0]}" "${OPTIONAL_DEPS[@]}"
  # mmdet3d's registry only, as the Makefile installs it (--no-deps: no compiled mmcv, no opencv-python), and
  # OpenPCDet's av2 / kornia and the VoD kit (the oracle of OpenPCDet's VoD evaluation) as the Makefile does
  "$env/bin/pip" install --quiet --no-deps mmengine==0.10.7 mmdet3d==1.4.0 mmdet==3.3.0 mmcv-lite==2.1.0 \
    "${pins[1]}" av2==0.3.6 kornia==0.6.8 vod-tudelft==1.0.3
  echo "$stamp" > "$env/.stamp"
  echo "  $name: installed in $((SECONDS - t0)) s ($(version_of "$env"))"
}

# make_py_env NAME PYTHON_VERSION BASE NUMPY_SPEC: that Python with BASE's torch version and only the test
# dependencies. The CUDA libraries (nvidia/, 2.5-3 GB, the same wheels for every Python) are BASE's,
# linked rather than unpacked again; everything Python-specific (torch, numpy) is this Python's own.
make_py_env() {
  local name=$1 pyv=$2 base=$COMPAT_DIR/$3 numpy_spec=$4 env=$COMPAT_DIR/$1 t0=$SECONDS
  local torch_version; torch_version=$("$base/bin/python" -c 'import torch; print(torch.__version__.split("+")[0])')
  local stamp="$pyv torch==$torch_version $numpy_spec ${TEST_DEPS[*]}"
  [ -f "$env/.stamp" ] && [ "$(cat "$env/.stamp")" = "$stamp" ] && { echo "  $name: reused ($(version_of "$env"))"; return; }
  rm -rf "$env" && "$(find_python "$pyv")" -m venv "$env"
  "$env/bin/pip" install --quiet --no-deps "torch==$torch_version"
  "$env/bin/pip" install --quiet "${TORCH_PURE_DEPS[@]}" "$numpy_spec" "${TEST_DEPS[@]}"
  local site; site=$("$env/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
  ln -s "$("$base/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')/nvidia" "$site/nvidia"
  echo "$stamp" > "$env/.stamp"
  echo "  $name: installed in $((SECONDS - t0)) s ($(version_of "$env"))"
}

# run_env NAME TESTS...: the suite in that environment, its summary line into $COMPAT_DIR/NAME.summary
run_env() {
  local name=$1; shift
  local env=$COMPAT_DIR/$name t0=$SECONDS rc=0
  # CI unset: what cannot run in these environments skips with its reason (counted, -rs) instead of failing as
  # it must in `make test`: the real mmdet3d (the mmcv wheel with compiled ops is built for the pinned torch
  # only), the Triton kernels and the CUDA test (make test, the device check; docs/compatibility.md)
  env -u CI "$env/bin/python" -m pytest -q -p no:cacheprovider -rs --ignore=tests/functional/test_triton_kernels.py \
    "$@" > "$COMPAT_DIR/$name.log" 2>&1 || rc=$?
  local summary; summary=$(tail -n 1 "$COMPAT_DIR/$name.log" | sed 's/=//g; s/^ *//; s/ *$//')
  echo "$name ($(version_of "$env")): $summary [$((SECONDS - t0)) s]$( [ $rc = 0 ] || echo "  FAILED, see $COMPAT_DIR/$name.log")" \
    > "$COMPAT_DIR/$name.summary"
  return $rc
}

# chain TORCH_ENV TORCH_SPEC NUMPY_SPEC PYTHON_VERSION...: that torch environment; then its suite, and beside it
# the Python environments on its torch, each installed (network and disk) and then checked, so that no core
# idles while another chain still runs. The floor's and the newest's chains run side by side (one torch
# thread per pytest, 2 cores).
chain() {
  local base=$1 torch_spec=$2 numpy_spec=$3 pyv rc=0 item runs=(); shift 3
  make_torch_env "$base" "$torch_spec" "$numpy_spec" > "$COMPAT_DIR/$base.install.log" 2>&1 &
  installed "$base" $! || return 1
  for pyv in "$@"; do
    { make_py_env "py$pyv" "$pyv" "$base" "$numpy_spec" > "$COMPAT_DIR/py$pyv.install.log" 2>&1 &
      installed "py$pyv" $! && run_env "py$pyv" "${PY_TESTS[@]}"; } & runs+=($!)
  done
  run_env "$base" "${CORE_TESTS[@]}" || rc=1
  for item in "${runs[@]}"; do wait "$item" || rc=1; done
  return $rc
}

# installed NAME PID: waits for that install; prints its line, or the log's tail when it failed
installed() {
  if wait "$2"; then grep -h "^  " "$COMPAT_DIR/$1.install.log" || true
  else echo "  $1: install FAILED"; tail -n 20 "$COMPAT_DIR/$1.install.log"; return 1; fi
}

mkdir -p "$COMPAT_DIR"
rm -f "$COMPAT_DIR"/*.summary
echo "compat_envs: installing and testing (logs in $COMPAT_DIR/*.log)"
t0=$SECONDS fail=0
chain torch-floor "$FLOOR_TORCH" "numpy<2" 3.9 3.10 & a=$!
chain torch-newest "$NEWEST_TORCH" numpy 3.12 3.13 & b=$!
wait $a || fail=1; wait $b || fail=1

echo "compat_envs: test counts per environment (the pinned torch: make test above); $((SECONDS - t0)) s in all"
for name in torch-floor torch-newest py3.9 py3.10 py3.12 py3.13; do
  cat "$COMPAT_DIR/$name.summary" 2>/dev/null || echo "$name: not run (its install failed)"
done
exit $fail
