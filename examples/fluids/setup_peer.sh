#!/usr/bin/env bash
# Builds the peer environment: JAX-SPH 0.1.0 (the SPH engine) and LagrangeBench 0.2.0 (its GNS
# and SEGNN, its metrics) in a virtual environment beside bgn's, never inside it.
#
#   bash examples/fluids/setup_peer.sh            # -> .venv-peer (git-ignored)
#   PEER_ENV=/some/where bash examples/fluids/setup_peer.sh
#
# Both packages declare Requires-Python "<=3.11", which by PEP 440 excludes 3.11.1 and later
# although they run there, and LagrangeBench pins a torch build PyPI does not serve; so their
# dependencies come from requirements-peer.txt and the two packages themselves are installed
# with --no-deps --ignore-requires-python. Nothing else is relaxed.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
env="${PEER_ENV:-.venv-peer}"
python3 -c 'import sys; assert sys.version_info[:2] == (3, 11), "the peer environment needs Python 3.11 (jax 0.4.29 wheels)"'
[ -x "$env/bin/python" ] || python3 -m venv "$env"
"$env/bin/pip" install -q -r "$here/requirements-peer.txt"
"$env/bin/pip" install -q --no-deps --ignore-requires-python jax-sph==0.1.0 lagrangebench==0.2.0
"$env/bin/python" - <<'PY'
import jax, jax_sph.solver, lagrangebench, ott
print(f"peer environment ready: jax {jax.__version__}, lagrangebench {lagrangebench.__version__ if hasattr(lagrangebench, '__version__') else '0.2.0'}, ott {ott.__version__}")
PY
