#!/usr/bin/env bash
# Stop the cluster that start.sh DIR brought up: cancel its jobs, then each daemon by the
# pid file in DIR/run (TERM, wait up to 10 s, then KILL). A pid is only signalled if that
# process really belongs to DIR (SLURM_CONF=DIR/slurm.conf in its environment, or
# --pid-file=DIR/run/... on its command line), so
# daemons not started from DIR are never touched. Idempotent: nothing running is fine.
# DIR gets the same checks as in start.sh (check_dir below; start.sh sources this file for
# them): a DIR that start.sh would refuse is refused here too (exit 2), since pid files in a
# folder that someone else can write could name any process.
#   usage: stop.sh DIR
set -euo pipefail

# --- which DIR is safe for root to use (shared with start.sh) ------------------------
# start.sh writes this file into DIR; only a DIR that has it, or is empty, is ever used
SLURM_LOCAL_MARKER=.ptovs-slurm-local

# refuse WHY...: DIR is not used; say why and exit 2 (nothing in it has been touched)
refuse() {
    echo "slurm-local: refusing DIR ${SLURM_LOCAL_ARG@Q}: $*" >&2
    echo "slurm-local: (see workflow/slurm-local/README.md, \"What DIR may be\")" >&2
    exit 2
}
# owner_mode PATH: set uid and mode (octal digits, e.g. 1777) of PATH itself (not a link's
# target); refuse if it cannot be read
owner_mode() {
    local st
    st=$(stat -c '%u %a' -- "$1") || refuse "cannot stat $1"
    [[ $st =~ ^([0-9]+)\ ([0-7]+)$ ]] || refuse "cannot stat $1"
    uid=${BASH_REMATCH[1]} mode=${BASH_REMATCH[2]}
}
# check_dir ARG [start]: resolve ARG to its physical path in DIR and set DIR_STATE to
# absent, empty or ours (holds the marker), or refuse. Root writes configs and the client
# wrappers on PATH into DIR, runs daemons from it and deletes its sub-paths on restart, so
# nobody but the caller may be able to change DIR or any directory above it: DIR is not
# a symlink, is owned by the caller, not writable by group or others; every directory
# above it is owned by root or the caller and not writable by group or others unless
# sticky (like /tmp). With "start", the directories above DIR must also be searchable by
# all, which munged insists on for the directories of its socket.
check_dir() {
    local arg=$1 for_start=${2:-} me p uid mode
    SLURM_LOCAL_ARG=$arg
    me=$(id -u)
    [[ -n $arg ]] || refuse "empty path"
    while [[ $arg == */ && $arg != / ]]; do arg=${arg%/}; done  # -L "link/" follows link
    [[ ! -L $arg ]] || refuse "it is a symbolic link"
    if [[ -e $arg ]]; then
        [[ -d $arg ]] || refuse "it is not a directory"
        DIR=$(cd -P -- "$arg" && pwd -P)
    else
        p=$(dirname -- "$arg")
        [[ -d $p ]] || refuse "its parent $p does not exist (DIR is created, its parents not)"
        p=$(cd -P -- "$p" && pwd -P)
        DIR=${p%/}/$(basename -- "$arg")
    fi
    [[ $DIR != / ]] || refuse "it is /"
    # slurm.conf, env.sh and the wrappers carry the path unquoted
    [[ $DIR =~ ^/[A-Za-z0-9._+/-]+$ ]] ||
        refuse "its path $DIR has characters other than letters, digits and . _ + - /"
    (( ${#DIR} <= 80 )) || refuse "path longer than 80 characters (unix socket paths are limited to 108 bytes)"
    p=$DIR
    while [[ $p != / ]]; do
        p=$(dirname -- "$p")
        owner_mode "$p"
        (( uid == 0 || uid == me )) ||
            refuse "$p, a directory above it, is owned by uid $uid (only root or uid $me may own them)"
        (( (8#$mode & 8#022) == 0 || (8#$mode & 8#1000) )) ||
            refuse "$p, a directory above it, is writable by group or others without the sticky bit (mode $mode)"
        [[ $for_start != start ]] || (( (8#$mode & 8#111) == 8#111 )) ||
            refuse "$p, a directory above it, is not searchable by all (mode $mode; munged needs that for its socket)"
    done
    if [[ ! -e $DIR ]]; then DIR_STATE=absent; return 0; fi
    owner_mode "$DIR"
    (( uid == me )) || refuse "it is owned by uid $uid, not by the caller (uid $me)"
    (( (8#$mode & 8#022) == 0 )) || refuse "it is writable by group or others (mode $mode)"
    local marker=$DIR/$SLURM_LOCAL_MARKER
    if [[ -f $marker && ! -L $marker ]] && owner_mode "$marker" && (( uid == me )); then
        DIR_STATE=ours
    elif [[ -z $(find "$DIR" -mindepth 1 -maxdepth 1 -print -quit) ]]; then
        DIR_STATE=empty
    else
        refuse "it is not empty and has no $SLURM_LOCAL_MARKER (it was not made by start.sh)"
    fi
}

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

main() {
    [[ $# -eq 1 ]] || { echo "usage: $0 DIR" >&2; exit 2; }
    [[ -e $1 || -L $1 ]] || exit 0
    check_dir "$1"
    [[ $DIR_STATE == ours ]] || exit 0  # empty: nothing was started from it
    export SLURM_CONF=$DIR/slurm.conf

    # Cancel still-running jobs while slurmctld is up, so their steps end cleanly.
    if ours "$(pidof_file slurmctld)"; then
        timeout 10 squeue -h -o %A 2>/dev/null | xargs -r timeout 10 scancel 2>/dev/null || true
    fi
    # Order: compute side first, the database and munge last (others need them to shut down).
    stop_pids "$(pidof_file slurmd)"
    # leftover job step daemons (slurmstepd inherits SLURM_CONF=DIR/slurm.conf); no pgrep,
    # procps may be missing in a minimal container
    local f stepds=()
    for f in /proc/[0-9]*/comm; do
        [[ $(cat "$f" 2>/dev/null) == slurmstepd ]] && stepds+=("$(basename "$(dirname "$f")")")
    done
    stop_pids "${stepds[@]}"
    stop_pids "$(pidof_file slurmctld)"
    stop_pids "$(pidof_file slurmdbd)"
    stop_pids "$(pidof_file mariadbd)"
    stop_pids "$(pidof_file munged)"
}

# start.sh sources this file for check_dir; only stop.sh runs main
if [[ ${BASH_SOURCE[0]} == "$0" ]]; then
    main "$@"
    exit 0
fi
