#!/usr/bin/env bash
# Validates deploy/k8s/*.yaml against the Kubernetes API schemas (strict: unknown
# fields are errors) with kubernetes-validate from PyPI, installed into its own
# virtual environment under target/. Run by .ci/run.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/k8s-validate-venv
if [ ! -x "$venv/bin/kubernetes-validate" ]; then
  echo "== installing kubernetes-validate into $venv"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet --disable-pip-version-check "kubernetes-validate==1.37.0"
fi
"$venv/bin/kubernetes-validate" --strict --kubernetes-version 1.34.0 deploy/k8s/*.yaml
