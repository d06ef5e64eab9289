#!/usr/bin/env bash
# Set up lc_petsc on Debian bookworm: Debian's PETSc/petsc4py/MPI/h5py stack, then a
# virtual environment (.venv) from the system interpreter that sees those packages, with
# lc_petsc installed editable. Safe to run again: every step is skipped when already done.
#
#   bash scripts/setup.sh            # install
#   bash scripts/setup.sh --demo     # install, then run configs/hairball_demo.toml under
#                                    # mpiexec -n 2 into out/hairball_demo (one to two minutes on
#                                    # 2 quiet cores; ccd contact, configs/hairball_demo.toml)
#   LC_PETSC_VENV=/path bash ...     # put the environment elsewhere
set -euo pipefail

demo=0
for arg in "$@"; do
  case "$arg" in
    --demo) demo=1 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "setup: unknown argument '$arg' (expected --demo)" >&2; exit 2 ;;
  esac
done

here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${LC_PETSC_VENV:-$here/.venv}
petsc_dir=/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real
debs=(python3-petsc4py-real python3-mpi4py python3-h5py-mpi python3-numpy python3-scipy
      python3-threadpoolctl python3-venv python3-pip openmpi-bin)

sudo_cmd=()
if [ "$(id -u)" -ne 0 ]; then sudo_cmd=(sudo); fi

missing=()
for p in "${debs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing Debian packages: ${missing[*]}"
  "${sudo_cmd[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

# petsc4py is built for Debian's /usr/bin/python3 only, so the venv must come from it.
if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating $venv"
  /usr/bin/python3 -m venv --system-site-packages "$venv"
fi
site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
# Debian's petsc4py.pth looks in /usr/lib/petsc (only present with petsc-dev) unless
# PETSC_DIR is exported; this .pth makes the real build importable with nothing exported,
# in every process that runs this interpreter (mpiexec ranks included).
echo "$petsc_dir/lib/python3/dist-packages" > "$site/lc_petsc_petsc4py.pth"

# pip must never replace Debian's NumPy: petsc4py is compiled against it.
numpy_version=$(/usr/bin/python3 -c 'import numpy; print(numpy.__version__)')
constraints="$venv/constraints.txt"
echo "numpy==$numpy_version" > "$constraints"

stamp="$venv/.lc_petsc_installed"
if [ ! -f "$stamp" ] || [ "$here/pyproject.toml" -nt "$stamp" ]; then
  echo "setup: installing lc_petsc (editable) into $venv"
  PIP_CONSTRAINT="$constraints" "$venv/bin/pip" install -q --disable-pip-version-check \
    -e "$here[test]"
  touch "$stamp"
fi

LC_NUMPY="$numpy_version" "$venv/bin/python" - <<'PY'
import os
import numpy, petsc4py
from petsc4py import PETSc
import h5py, matplotlib, tqdm  # noqa: F401  (the main job's dependencies)
from pxr import Usd, UsdGeom, Vt, Gf  # noqa: F401  (usd-core, beside Debian's NumPy)
import lc_petsc
assert numpy.__version__ == os.environ["LC_NUMPY"], (
    f"pip replaced Debian's NumPy {os.environ['LC_NUMPY']} by {numpy.__version__}")
print(f"setup: ok: lc_petsc {lc_petsc.__version__}, PETSc {'.'.join(map(str, PETSc.Sys.getVersion()))}, "
      f"petsc4py {petsc4py.__version__}, NumPy {numpy.__version__}")
PY

# Numba's kernels compiled here once (cached in the tree), not in the first run or test
echo "setup: compiling the Numba kernels (the first time only: a few minutes; cached)"
"$venv/bin/python" -m lc_petsc.elements.warm

if [ "$demo" -eq 1 ]; then
  echo "setup: running the demo: mpiexec -n 2 drivers/simulate.py configs/hairball_demo.toml --out out/hairball_demo"
  cd "$here"
  OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 \
    mpiexec --oversubscribe -n 2 "$venv/bin/python" drivers/simulate.py configs/hairball_demo.toml \
    --out out/hairball_demo
fi
