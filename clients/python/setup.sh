#!/usr/bin/env bash
# Makes clients/python ready: a virtual environment with grpcio, and the Python stubs
# generated from proto/cutsim.proto (into generated/, not committed).
set -euo pipefail
cd "$(dirname "$0")"
if [ ! -x .venv/bin/python ]; then
    python3 -m venv .venv
fi
.venv/bin/pip install --quiet --disable-pip-version-check -r requirements.txt
mkdir -p generated
.venv/bin/python -m grpc_tools.protoc -I ../../proto --python_out=generated --grpc_python_out=generated ../../proto/cutsim.proto
echo "ready: clients/python/.venv/bin/python run_script.py --help"
