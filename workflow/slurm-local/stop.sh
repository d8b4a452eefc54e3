#!/usr/bin/env bash
# Stop the cluster that start.sh DIR brought up: cancel its jobs, then each daemon by the
# pid file in DIR/run (TERM, wait up to 10 s, then KILL). A pid is only signalled if that
# process really belongs to DIR (SLURM_CONF=DIR/slurm.conf in its environment, or
# --pid-file=DIR/run/... on its command line), so
# daemons not started from DIR are never touched. Idempotent: nothing running is fine.
#   usage: stop.sh DIR
set -euo pipefail

[[ $# -eq 1 ]] || { echo "usage: $0 DIR" >&2; exit 2; }
[[ -d $1 ]] || exit 0
DIR=$(cd "$1" && pwd)
export SLURM_CONF=$DIR/slurm.conf

# alive PID: the process exists and is not a zombie (an exited daemon whose new parent,
# PID 1, has not reaped it yet)
alive() { [[ -r /proc/$1/stat ]] && [[ $(awk '{print $3}' "/proc/$1/stat" 2>/dev/null) != Z ]]; }
# ours PID: true if PID is alive and was started from DIR (slurm daemons and their
# slurmstepds carry SLURM_CONF; munged and mariadbd were given --pid-file). No grep -q:
# under pipefail its early exit could make tr fail with SIGPIPE.
ours() {
    [[ $1 =~ ^[0-9]+$ ]] && alive "$1" &&
        cat "/proc/$1/cmdline" "/proc/$1/environ" 2>/dev/null | tr '\0' '\n' |
        grep -xF >/dev/null -e "SLURM_CONF=$DIR/slurm.conf" -e "--pid-file=$DIR/run/munged.pid" \
                  -e "--pid-file=$DIR/run/mariadbd.pid"
}
# stop_pids PID...: TERM those that are ours, wait up to 10 s, then KILL what is left
stop_pids() {
    local p pids=()
    for p in "$@"; do ours "$p" && pids+=("$p"); done
    (( ${#pids[@]} )) || return 0
    kill -TERM "${pids[@]}" 2>/dev/null || true
    for _ in $(seq 50); do
        local left=0
        for p in "${pids[@]}"; do alive "$p" && left=1; done
        (( left )) || return 0
        sleep 0.2
    done
    kill -KILL "${pids[@]}" 2>/dev/null || true
}
pidof_file() { cat "$DIR/run/$1.pid" 2>/dev/null || true; }

# Cancel still-running jobs while slurmctld is up, so their steps end cleanly.
if ours "$(pidof_file slurmctld)"; then
    timeout 10 squeue -h -o %A 2>/dev/null | xargs -r timeout 10 scancel 2>/dev/null || true
fi
# Order: compute side first, the database and munge last (others need them to shut down).
stop_pids "$(pidof_file slurmd)"
# leftover job step daemons (slurmstepd inherits SLURM_CONF=DIR/slurm.conf); no pgrep,
# procps may be missing in a minimal container
stepds=()
for f in /proc/[0-9]*/comm; do
    [[ $(cat "$f" 2>/dev/null) == slurmstepd ]] && stepds+=("$(basename "$(dirname "$f")")")
done
stop_pids "${stepds[@]}"
stop_pids "$(pidof_file slurmctld)"
stop_pids "$(pidof_file slurmdbd)"
stop_pids "$(pidof_file mariadbd)"
stop_pids "$(pidof_file munged)"
exit 0
