#!/usr/bin/env bash
# The Python package's CI: builds it into a fresh virtual environment, as a user would
# (`pip install ./python`), with NumPy, pytest, Ray and torch, and runs its pytest suite (the
# NumPy API, the torch autograd tests, the Ray tests). Prints how long each install took.
#
# torch comes from PyPI, whose Linux wheel is the CUDA build (about 4 GB with its nvidia-*
# libraries): PyTorch's CPU-only index is not reachable from this machine. The tests run on
# the CPU either way.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cd "$here"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
python3 -m venv "$work/venv"
py="$work/venv/bin/python"

t0=$(date +%s)
"$py" -m pip install -q numpy pytest ray torch
t1=$(date +%s)
"$py" -m pip install -q .
t2=$(date +%s)
echo "python/ci.sh: numpy, pytest, ray, torch installed in $((t1 - t0)) s; diffluid built and installed in $((t2 - t1)) s"
# The CLI, when the root's `cargo test --release` has built it: the exceptions' messages are
# compared with what it prints.
if [ -x ../target/release/diffluid ]; then
    export DIFFLUID_CLI="$here/../target/release/diffluid"
fi
# Away from the source folder (whose diffluid/ has no compiled module), so that Python
# imports the installed package.
cd "$work"
"$py" -c "import diffluid, torch, ray; print('diffluid', diffluid.__version__, 'from', diffluid.__file__, '| torch', torch.__version__, '| ray', ray.__version__)"
"$work/venv/bin/pytest" -q -p no:cacheprovider "$here/tests"
