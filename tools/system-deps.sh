#!/usr/bin/env bash
# The system packages the test suite needs, on Debian or Ubuntu (`make system-deps`,
# run by `make test` and by .ci/run):
#   g++                          the compiled CPU rasterizer (built on first use)
#   chromium                     the browser viewer's test (Debian's, never a download)
#   slurm-wlm slurmdbd munge     the workflow's test on a single-node Slurm with
#   mariadb-server               accounting (started by the test itself)
# Installs what is missing when run as root; otherwise names the one command to run
# and fails, before the suite starts.
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
if ! command -v apt-get >/dev/null 2>&1; then
  echo "the tests need these system packages (Debian names): ${missing[*]};" \
       "install them with your package manager, then rerun" >&2
  exit 1
fi
if [ "$(id -u)" -ne 0 ]; then
  echo "the tests need these system packages: ${missing[*]}; run:" >&2
  echo "  sudo apt-get install -y ${missing[*]}    (or: sudo make system-deps)" >&2
  exit 1
fi
echo "installing ${missing[*]}"
apt-get update -qq
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
