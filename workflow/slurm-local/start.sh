#!/usr/bin/env bash
# Bring up a throwaway single-node Slurm cluster (munged, mariadbd, slurmdbd, slurmctld,
# slurmd) with job accounting, everything inside DIR, listening on loopback only.
# DIR must be new, empty or made by an earlier start.sh, and only root (the caller) may be
# able to change it or any directory above it; anything else is refused (exit 2) before
# anything is written, removed or started (see check_dir in stop.sh, and README.md).
# Runs as root, writes its own configs (nothing from /etc/slurm or /etc/munge is used).
#   usage: start.sh DIR      then: source DIR/env.sh; sbatch ...; sacct ...
#   stop with: stop.sh DIR   (start.sh also calls it first, so a re-run restarts cleanly)
# START_TIMEOUT (seconds, default 90) bounds the whole wait for the daemons.
set -euo pipefail

[[ $# -eq 1 ]] || { echo "usage: $0 DIR" >&2; exit 2; }
[[ $(id -u) -eq 0 ]] || { echo "$0: must run as root" >&2; exit 2; }
HERE=$(cd "$(dirname "$0")" && pwd)
DEADLINE=$((SECONDS + ${START_TIMEOUT:-90}))
for exe in munged mungekey mariadbd mariadb-install-db mariadb slurmdbd slurmctld slurmd \
           sacctmgr sinfo sacct srun sbatch squeue scancel scontrol sshare python3; do
    command -v "$exe" >/dev/null || { echo "$0: $exe not found (see README.md)" >&2; exit 1; }
done

# Is DIR safe for root to write, run from and clean? Refuses (exit 2) before anything is
# written, removed or started; sets DIR (physical path) and DIR_STATE (absent, empty, ours).
# shellcheck source=SCRIPTDIR/stop.sh
source "$HERE/stop.sh"
check_dir "$1" start

# Loopback only. With CommunicationParameters=NoInAddrAny (NoCtldInAddrAny for slurmctld)
# Slurm binds its daemons (and srun) not to INADDR_ANY but to the first IPv4 address that
# this machine's host name (gethostname) resolves to, as below; so that address must be a
# loopback one, and the whole cluster uses it (SlurmctldHost, NodeAddr, slurmdbd).
ADDR=$(python3 -c '
import socket
flags = socket.AI_ADDRCONFIG | socket.AI_NUMERICSERV | socket.AI_PASSIVE | socket.AI_CANONNAME
print(socket.getaddrinfo(socket.gethostname(), "0", socket.AF_INET, socket.SOCK_STREAM,
                         0, flags)[0][4][0])' 2>/dev/null) || ADDR=
if [[ ! $ADDR =~ ^127\.[0-9.]+$ ]]; then
    echo "$0: the host name $(uname -n) resolves to '${ADDR:-nothing}', not to a loopback" \
         "address; Slurm binds its daemons to that address, which would make them reachable" \
         "from the network. Map the host name to 127.0.1.1 in /etc/hosts (first line" \
         "that names it)." >&2
    exit 1
fi

# DIR is created 711: munged needs every directory above its socket searchable by all;
# nobody else may list or write it. Not mkdir -p: its parent was checked, nothing above.
if [[ $DIR_STATE == absent ]]; then
    mkdir -m 711 -- "$DIR" || refuse "could not create it"
fi
chmod 711 "$DIR"
[[ $DIR_STATE == ours ]] || echo "made by workflow/slurm-local/start.sh" > "$DIR/$SLURM_LOCAL_MARKER"

# Anything left over from an earlier run in DIR: stop it and start from a clean slate
# (only our own sub-paths are removed, never DIR itself).
"$HERE/stop.sh" "$DIR"
rm -rf "${DIR:?}"/{munge,mysql,state,spool,log,run,bin} "$DIR"/{slurm.conf,slurmdbd.conf,env.sh}
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
# free TCP ports on ADDR (all held open while choosing, so they differ)
read -r DB_PORT DBD_PORT CTLD_PORT SLURMD_PORT < <(python3 -c '
import socket, sys
ss = [socket.socket() for _ in range(4)]
for s in ss: s.bind((sys.argv[1], 0))
print(*(s.getsockname()[1] for s in ss))' "$ADDR")

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
SlurmctldHost=$HOST($ADDR)
CommunicationParameters=NoCtldInAddrAny,NoInAddrAny
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
JobAcctGatherFrequency=1
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=$ADDR
AccountingStoragePort=$DBD_PORT
AccountingStoragePass=$MUNGE_SOCK
AccountingStoreFlags=job_comment   # sacct shows the workflow's rule and scene (--comment)
JobCompType=jobcomp/none
InactiveLimit=0
KillWait=5
MinJobAge=300
NodeName=$HOST NodeAddr=$ADDR CPUs=$NCPU RealMemory=$MEM_MB State=UNKNOWN
# one node, two partitions; "gpu" has no real GRES, it stands in for a GPU partition
PartitionName=cpu Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$HOST MaxTime=INFINITE State=UP
EOF

# slurmdbd insists on mode 600 (it holds the DB password); it is found next to slurm.conf
(umask 077; cat > "$DIR/slurmdbd.conf" <<EOF
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCK
DbdHost=localhost
DbdAddr=$ADDR
CommunicationParameters=NoInAddrAny
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
# shellcheck disable=SC2016  # $PATH is expanded where env.sh is sourced
printf 'export SLURM_CONF=%s\nexport PATH=%s:$PATH\n' "$SLURM_CONF" "$DIR/bin" > "$DIR/env.sh"

# --- munged --------------------------------------------------------------------------
# No --force: munged checks that the key is 0600 and the dirs of key, socket, seed and log
# are not writable by others, and that the socket's dirs are searchable by all (DIR 711).
mungekey --create --keyfile="$DIR/munge/munge.key" >/dev/null
munged --socket="$MUNGE_SOCK" --key-file="$DIR/munge/munge.key" \
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
# the password goes in on stdin, never in a command line (ps shows those to every user)
"${MYSQL[@]}" <<EOF || fail mariadbd
CREATE USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
EOF

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
