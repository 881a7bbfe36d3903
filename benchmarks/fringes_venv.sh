#!/usr/bin/env bash
# The `fringes` comparison's own environment. fringes is GPL: it lives only here,
# never in PTP Studio's environment or dependencies, and ptpcore never imports it.
#   bash benchmarks/fringes_venv.sh [/tmp/fringes-venv]
set -euo pipefail
VENV="${1:-/tmp/fringes-venv}"
python3 -m venv "$VENV"
"$VENV/bin/pip" install --no-deps fringes
"$VENV/bin/pip" install numba scikit-image sympy pyyaml opencv-contrib-python-headless numpy scipy
"$VENV/bin/python" -c "import fringes, numba; print('fringes', fringes.__version__, 'numba', numba.__version__)"
