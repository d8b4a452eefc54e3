#!/usr/bin/env bash
# The system packages the test suite needs, on Debian or Ubuntu (`make system-deps`,
# run first by `make test`, and by .ci/run):
#   g++                          the compiled CPU rasterizer (built on first use)
#   chromium                     the browser viewer's test (Debian's, never a download)
#   slurm-wlm slurmdbd munge     the workflow's test on a single-node Slurm with
#   mariadb-server               accounting (started by the test itself)
# As root it installs what is missing. Otherwise it says in one line which are
# missing and the one command that installs them, and exits 0: the suite runs, and
# the tests that need them are skipped (tests/conftest.py names them at the end).
# Where they are required (CI=true, or PTOVS_REQUIRE_SYSTEM_DEPS=1) a missing
# package it cannot install stops here with exit 1, and its tests fail, never skip.
set -euo pipefail
declare -A need=(
  [g++]=g++ [chromium]=chromium [slurmctld]=slurm-wlm [slurmdbd]=slurmdbd
  [munged]=munge [mariadbd]=mariadb-server
)
missing=()
for bin in g++ chromium slurmctld slurmdbd munged mariadbd; do
  command -v "$bin" >/dev/null 2>&1 || missing+=("${need[$bin]}")
done
if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
required=0
case "${CI:-}" in 1 | true | TRUE | True | yes) required=1 ;; esac
[ "${PTOVS_REQUIRE_SYSTEM_DEPS:-}" = 1 ] && required=1
if ! command -v apt-get >/dev/null 2>&1; then
  how="install them with your package manager (Debian names)"
elif [ "$(id -u)" -ne 0 ]; then
  how="install them: sudo make system-deps"
else
  echo "installing ${missing[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
  exit 0
fi
if [ "$required" -eq 1 ]; then
  echo "the tests need these system packages: ${missing[*]}; $how" \
       "(required here: CI or PTOVS_REQUIRE_SYSTEM_DEPS=1)" >&2
  exit 1
fi
echo "system packages missing: ${missing[*]}; their tests are skipped; $how" >&2
