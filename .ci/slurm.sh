#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for the tests marked `slurm` (tests/test_slurm.py).
#
#   bash .ci/slurm.sh start   # as root (or with sudo): install (Debian/Ubuntu), configure and start it; prints its state
#   bash .ci/slurm.sh stop    # stop every daemon it started
#
# Debian's slurm-wlm 22.05, munge for authentication, and accounting through slurmdbd on a local
# MariaDB, so `sacct` answers (submitit polls job states with it; without accounting a cancelled
# job's state is unknown and every poll prints a warning). Everything lives in $DRONE_SLURM_DIR
# (default /tmp/drone-slurm): configs, logs, state, the database. No cgroup plugins (linuxproc
# process tracking, no task plugin): it runs inside containers.
#
# If the scheduler cannot start (no root, no apt-get, a daemon that does not come up), `start`
# writes the reason into $DRONE_SLURM_DIR/unavailable, prints it and exits 1; the slurm tests then
# skip with that reason.
set -uo pipefail

DIR=${DRONE_SLURM_DIR:-/tmp/drone-slurm}
CONF=/etc/slurm
CLUSTER=drone
HOST=$(hostname -s)

unavailable() {
    mkdir -p "$DIR"
    echo "$*" > "$DIR/unavailable"
    echo "slurm: not available: $*" >&2
    exit 1
}

wait_for() {  # wait_for <seconds> <what> <command...>
    local seconds=$1 what=$2
    shift 2
    for _ in $(seq "$((seconds * 4))"); do
        "$@" > /dev/null 2>&1 && return 0
        sleep 0.25
    done
    unavailable "$what did not come up within ${seconds} s (logs in $DIR)"
}

start() {
    [ "$(id -u)" = 0 ] || unavailable "starting the daemons needs root"
    rm -f "$DIR/unavailable"
    local missing=()
    for tool in sbatch slurmctld slurmd slurmdbd munged mariadbd; do
        command -v "$tool" > /dev/null || [ -x "/usr/sbin/$tool" ] || missing+=("$tool")
    done
    if [ ${#missing[@]} -gt 0 ]; then
        command -v apt-get > /dev/null || unavailable "missing ${missing[*]} and no apt-get to install them"
        echo "slurm: installing slurm-wlm slurmdbd munge mariadb-server (missing: ${missing[*]})"
        export DEBIAN_FRONTEND=noninteractive
        apt-get install -y -q slurm-wlm slurmdbd munge mariadb-server > "$DIR.apt.log" 2>&1 \
            || { apt-get update -q > /dev/null 2>&1 \
                && apt-get install -y -q slurm-wlm slurmdbd munge mariadb-server > "$DIR.apt.log" 2>&1; } \
            || unavailable "apt-get install failed (see $DIR.apt.log)"
    fi
    stop > /dev/null 2>&1
    mkdir -p "$DIR"/{ctld,d,db} "$CONF" /run/munge /run/mysqld
    chown munge:munge /run/munge
    chown mysql:mysql /run/mysqld "$DIR/db"

    # munge: a key, and the daemon as its own user.
    [ -s /etc/munge/munge.key ] || mungekey --create --keyfile=/etc/munge/munge.key \
        || unavailable "cannot create /etc/munge/munge.key"
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
    runuser -u munge -- /usr/sbin/munged --force || unavailable "munged did not start"
    wait_for 10 munged munge -n

    # MariaDB for slurmdbd, its files under $DIR/db.
    if [ ! -d "$DIR/db/mysql" ]; then
        mariadb-install-db --user=mysql --datadir="$DIR/db" > "$DIR/mariadb-install.log" 2>&1 \
            || unavailable "mariadb-install-db failed (see $DIR/mariadb-install.log)"
    fi
    (mariadbd --user=mysql --datadir="$DIR/db" --socket=/run/mysqld/mysqld.sock \
        --pid-file=/run/mysqld/mariadb.pid --skip-networking=0 --bind-address=127.0.0.1 \
        > "$DIR/mariadb.log" 2>&1 &)
    wait_for 30 MariaDB mariadb -e "SELECT 1"
    mariadb -e "CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'slurm';
                GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost'; FLUSH PRIVILEGES;" \
        || unavailable "cannot create the slurm database user"

    # slurmdbd, then the cluster in its database.
    cat > "$CONF/slurmdbd.conf" <<EOF
AuthType=auth/munge
DbdHost=localhost
SlurmUser=root
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=slurm
StorageLoc=slurm_acct_db
LogFile=$DIR/slurmdbd.log
PidFile=$DIR/slurmdbd.pid
EOF
    chmod 600 "$CONF/slurmdbd.conf"
    /usr/sbin/slurmdbd || unavailable "slurmdbd did not start (see $DIR/slurmdbd.log)"

    # One node: this machine, its cores, 80% of its memory.
    local cpus mem
    cpus=$(nproc)
    mem=$(awk '/MemTotal/ {print int($2 / 1024 * 0.8)}' /proc/meminfo)
    cat > "$CONF/slurm.conf" <<EOF
ClusterName=$CLUSTER
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$DIR/ctld
SlurmdSpoolDir=$DIR/d
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
ReturnToService=2
MpiDefault=none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
JobCompType=jobcomp/none
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
# Short cycles: a test cluster that reacts within seconds.
SchedulerParameters=sched_interval=2
MinJobAge=600
KillWait=5
NodeName=$HOST CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
    wait_for 20 slurmdbd sacctmgr -n list cluster
    sacctmgr -i add cluster "$CLUSTER" > /dev/null 2>&1 || true
    /usr/sbin/slurmctld || unavailable "slurmctld did not start (see $DIR/slurmctld.log)"
    /usr/sbin/slurmd || unavailable "slurmd did not start (see $DIR/slurmd.log)"
    wait_for 30 "the node" sh -c "sinfo -h -o %T | grep -qE '^(idle|mixed|allocated)'"
    wait_for 20 "accounting" sacct -n -X
    echo "slurm: cluster '$CLUSTER' up: node $HOST, $cpus CPUs, ${mem} MB; accounting via slurmdbd"
    sinfo
}

stop() {
    for pid in "$DIR"/slurmd.pid "$DIR"/slurmctld.pid "$DIR"/slurmdbd.pid /run/mysqld/mariadb.pid; do
        [ -s "$pid" ] && kill "$(cat "$pid")" 2> /dev/null
    done
    pkill -x slurmd; pkill -x slurmctld; pkill -x slurmdbd; pkill -x mariadbd
    pkill -x munged
    sleep 1
    echo "slurm: stopped"
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    *) echo "usage: $0 start|stop" >&2; exit 2 ;;
esac
