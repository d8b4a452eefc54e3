#!/usr/bin/env bash
# Bring up a throwaway single-node Slurm cluster (munged, mariadbd, slurmdbd, slurmctld,
# slurmd) with job accounting, everything inside DIR, listening on 127.0.0.1 only.
# Runs as root, writes its own configs (nothing from /etc/slurm or /etc/munge is used).
#   usage: start.sh DIR      then: source DIR/env.sh; sbatch ...; sacct ...
#   stop with: stop.sh DIR   (start.sh also calls it first, so a re-run restarts cleanly)
# START_TIMEOUT (seconds, default 90) bounds the whole wait for the daemons.
set -euo pipefail

[[ $# -eq 1 ]] || { echo "usage: $0 DIR" >&2; exit 2; }
[[ $(id -u) -eq 0 ]] || { echo "$0: must run as root" >&2; exit 2; }
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$1"
DIR=$(cd "$1" && pwd)
DEADLINE=$((SECONDS + ${START_TIMEOUT:-90}))
for exe in munged mungekey mariadbd mariadb-install-db mariadb slurmdbd slurmctld slurmd \
           sacctmgr sinfo sacct srun sbatch squeue scancel scontrol sshare python3; do
    command -v "$exe" >/dev/null || { echo "$0: $exe not found (see README.md)" >&2; exit 1; }
done
# unix socket paths are limited to 108 bytes
(( ${#DIR} <= 80 )) || { echo "$0: DIR path too long for unix sockets: $DIR" >&2; exit 2; }

# Anything left over from an earlier run in DIR: stop it and start from a clean slate
# (only our own sub-paths are removed, never DIR itself).
"$HERE/stop.sh" "$DIR"
rm -rf "$DIR"/{munge,mysql,state,spool,log,run,bin} "$DIR"/{slurm.conf,slurmdbd.conf,env.sh}
mkdir -p "$DIR"/{munge,mysql,state,spool,log,run}
chmod 755 "$DIR/munge"  # key stays 600; socket usable by all local users

# --- helpers -------------------------------------------------------------------------
# fail NAME: say which daemon failed, show its log, tear everything down, exit 1
fail() {
    echo "start.sh: $1 failed to come up (log: $DIR/log/$1.log)" >&2
    tail -n 40 "$DIR/log/$1.log" "$DIR/log/$1.out" >&2 2>/dev/null || true
    "$HERE/stop.sh" "$DIR" >/dev/null 2>&1 || true
    exit 1
}
# wait_for NAME CMD...: retry CMD until it succeeds; fail NAME on timeout or if the
# daemon's pid file names a process that has died
wait_for() {
    local name=$1; shift
    until "$@" >/dev/null 2>&1; do
        local pidf=$DIR/run/$name.pid
        if (( SECONDS > DEADLINE )); then fail "$name"; fi
        if [[ -s $pidf ]] && ! kill -0 "$(cat "$pidf")" 2>/dev/null; then fail "$name"; fi
        sleep 0.5
    done
}
# N free TCP ports on 127.0.0.1 (all held open while choosing, so they differ)
read -r DB_PORT DBD_PORT CTLD_PORT SLURMD_PORT < <(python3 -c '
import socket
ss = [socket.socket() for _ in range(4)]
for s in ss: s.bind(("127.0.0.1", 0))
print(*(s.getsockname()[1] for s in ss))')

HOST=$(uname -n); HOST=${HOST%%.*}   # short host name (no need for `hostname`)
NCPU=$(nproc)
# RealMemory: 90 % of the currently available memory, in MB
MEM_MB=$(awk '/^MemAvailable:/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
MUNGE_SOCK=$DIR/munge/munge.socket
DB_SOCK=$DIR/run/mariadb.sock
DB_PASS=$(head -c 12 /dev/urandom | od -An -tx1 | tr -d ' \n')
export SLURM_CONF=$DIR/slurm.conf

# --- configs -------------------------------------------------------------------------
cat > "$DIR/slurm.conf" <<EOF
ClusterName=ptovs
SlurmctldHost=$HOST(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$MUNGE_SOCK
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/run/slurmctld.pid
SlurmdPidFile=$DIR/run/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
MailProg=/bin/true
MpiDefault=none
ReturnToService=2
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=2
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStoragePort=$DBD_PORT
AccountingStoragePass=$MUNGE_SOCK
AccountingStoreFlags=job_comment   # sacct shows the workflow's rule and scene (--comment)
JobCompType=jobcomp/none
InactiveLimit=0
KillWait=5
MinJobAge=300
NodeName=$HOST NodeAddr=127.0.0.1 CPUs=$NCPU RealMemory=$MEM_MB State=UNKNOWN
# one node, two partitions; "gpu" has no real GRES, it stands in for a GPU partition
PartitionName=cpu Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$HOST MaxTime=INFINITE State=UP
EOF

# slurmdbd insists on mode 600 (it holds the DB password); it is found next to slurm.conf
(umask 077; cat > "$DIR/slurmdbd.conf" <<EOF
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCK
DbdHost=localhost
DbdAddr=127.0.0.1
DbdPort=$DBD_PORT
SlurmUser=root
PidFile=$DIR/run/slurmdbd.pid
LogFile=$DIR/log/slurmdbd.log
DebugLevel=info
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$DB_PORT
StorageUser=slurm
StoragePass=$DB_PASS
StorageLoc=slurm_acct_db
EOF
)

# Clients find this cluster through SLURM_CONF. Snakemake's Slurm job step strips every
# SLURM_* variable (SLURM_CONF too) before its inner srun, which on a real cluster then
# reads /etc/slurm; here the client commands on PATH are wrappers that set it.
mkdir -p "$DIR/bin"
for exe in srun sbatch squeue scancel sacct sinfo scontrol sacctmgr sshare; do
    printf '#!/bin/sh\nSLURM_CONF=%s exec %s "$@"\n' "$SLURM_CONF" "$(command -v "$exe")" \
        > "$DIR/bin/$exe"
    chmod 755 "$DIR/bin/$exe"
done
printf 'export SLURM_CONF=%s\nexport PATH=%s:$PATH\n' "$SLURM_CONF" "$DIR/bin" > "$DIR/env.sh"

# --- munged --------------------------------------------------------------------------
mungekey --create --keyfile="$DIR/munge/munge.key" --force >/dev/null
munged --force --socket="$MUNGE_SOCK" --key-file="$DIR/munge/munge.key" \
    --pid-file="$DIR/run/munged.pid" --log-file="$DIR/log/munged.log" \
    --seed-file="$DIR/munge/munged.seed" </dev/null >"$DIR/log/munged.out" 2>&1 || fail munged
wait_for munged test -S "$MUNGE_SOCK"

# --- mariadbd (own datadir, socket and TCP port; root logs in via its unix socket) ---
mariadb-install-db --no-defaults --user=root --datadir="$DIR/mysql" \
    --auth-root-authentication-method=socket --skip-test-db \
    >"$DIR/log/mariadb-install.log" 2>&1 || fail mariadb-install
setsid mariadbd --no-defaults --user=root --datadir="$DIR/mysql" --socket="$DB_SOCK" \
    --bind-address=127.0.0.1 --port="$DB_PORT" --skip-name-resolve \
    --pid-file="$DIR/run/mariadbd.pid" --log-error="$DIR/log/mariadbd.log" \
    --innodb-buffer-pool-size=512M --innodb-log-file-size=64M --innodb-lock-wait-timeout=900 \
    </dev/null >"$DIR/log/mariadbd.out" 2>&1 &
MYSQL=(mariadb --no-defaults --socket="$DB_SOCK" -uroot)
wait_for mariadbd "${MYSQL[@]}" -e 'SELECT 1'
"${MYSQL[@]}" -e "CREATE USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
    GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';" || fail mariadbd

# --- slurmdbd, then register cluster / account / user --------------------------------
slurmdbd </dev/null >"$DIR/log/slurmdbd.out" 2>&1 || fail slurmdbd
wait_for slurmdbd sacctmgr -n list cluster
sacctmgr -i add cluster ptovs >/dev/null
sacctmgr -i add account ptovs Cluster=ptovs Description=ptovs Organization=ptovs >/dev/null
sacctmgr -i add user root Account=ptovs Cluster=ptovs >/dev/null

# --- slurmctld, slurmd ---------------------------------------------------------------
slurmctld </dev/null >"$DIR/log/slurmctld.out" 2>&1 || fail slurmctld
wait_for slurmctld scontrol ping
slurmd -N "$HOST" </dev/null >"$DIR/log/slurmd.out" 2>&1 || fail slurmd
node_idle() { [[ $(sinfo -h -N -n "$HOST" -o %t | sort -u) == idle ]]; }
wait_for slurmd node_idle
wait_for slurmdbd sacct -n -X -S now

echo "slurm-local: up in ${SECONDS}s (ClusterName=ptovs, partitions cpu/gpu, node $HOST)."
echo "slurm-local: source $DIR/env.sh"
