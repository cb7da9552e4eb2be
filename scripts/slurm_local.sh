#!/usr/bin/env bash
# A single-node SLURM cluster on localhost, to try and test the SLURM profile (profiles/slurm).
#
#   scripts/slurm_local.sh install [--accounting]   apt-get the Debian packages (root)
#   scripts/slurm_local.sh start [--accounting]     munged, slurmctld, slurmd (+ MariaDB and slurmdbd)
#   scripts/slurm_local.sh status                   which daemons run, sinfo
#   scripts/slurm_local.sh env                      prints `export SLURM_CONF=...` (for other hosts; not needed here)
#   scripts/slurm_local.sh stop [--purge]           cancels its jobs, stops its daemons (--purge: deletes its state)
#
# Needs root (slurmd starts the jobs' processes; the daemons run as root) and Debian's packages
# slurmctld slurmd slurm-client munge, with --accounting also slurmdbd mariadb-server
# (tested with SLURM 22.05.8, MariaDB 10.11, munge 0.5.15 on Debian 12).
#
# Everything lives in one folder, $WEAR_SLURM_DIR (default /var/lib/wear-slurm): its own munge key
# and socket, slurm.conf, spool and state, logs, the MariaDB data, so a host's own munge and
# MariaDB are left alone. One thing outside it: while the cluster runs, /etc/slurm/slurm.conf is a
# symlink to its slurm.conf (the executor plugin drops SLURM_CONF for the srun inside each job, so
# the commands there must find the config at the default path); `start` refuses to run on a host
# with a slurm.conf of its own. Ports: $WEAR_SLURM_PORT (default 6817) for slurmctld, +1 slurmd,
# +2 slurmdbd, +3 MariaDB (127.0.0.1 only).
#
# `start` is idempotent: daemons already running in the requested mode are left as they are; a
# cluster running in the other mode is restarted in the requested one (state kept).
# Memory (--mem) is enforced as on most clusters, by cgroups (task/cgroup, ConstrainRAMSpace: the
# kernel's OOM killer; the job log says "Out Of Memory") where a cgroup-v1 memory and freezer
# hierarchy is mounted; elsewhere (cgroup v2, for which SLURM 22.05 wants systemd/dbus; containers)
# by the accounting poller (JobAcctGatherParams=OverMemoryKill, every second; the log says
# "exceeded memory limit"). WEAR_SLURM_MEMORY_LIMIT=cgroup|poll chooses.
set -euo pipefail

D=${WEAR_SLURM_DIR:-/var/lib/wear-slurm}
PORT=${WEAR_SLURM_PORT:-6817}
CLUSTER=wearlocal
PARTITION=local
ACCOUNT=wear
export SLURM_CONF=$D/etc/slurm.conf
MUNGE_SOCKET=$D/munge/munge.socket
DB_SOCKET=$D/run/mariadb.sock

PACKAGES=(slurmctld slurmd slurm-client munge)
PACKAGES_ACCOUNTING=(slurmdbd mariadb-server)

say() { echo "slurm_local: $*" >&2; }
die() { say "$*"; exit 1; }

need_root() {
    [[ $(id -u) -eq 0 ]] || die "needs root (slurmd runs the jobs' processes; the daemons run as root): run it with sudo"
}

need_commands() {
    local missing=()
    for c in "$@"; do command -v "$c" >/dev/null 2>&1 || missing+=("$c"); done
    if ((${#missing[@]})); then
        die "missing ${missing[*]}: install Debian's packages ${PACKAGES[*]}${ACCOUNTING:+ ${PACKAGES_ACCOUNTING[*]}} (as root: $0 install${ACCOUNTING:+ --accounting})"
    fi
}

pid_of() {  # pid from a pid file, if that process is alive
    local f=$1 pid
    [[ -s $f ]] || return 1
    pid=$(<"$f")
    [[ $pid =~ ^[0-9]+$ ]] && kill -0 "$pid" 2>/dev/null && echo "$pid"
}

wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
    local limit=$1 what=$2 deadline=$((SECONDS + $1)); shift 2
    while ((SECONDS < deadline)); do
        "$@" >/dev/null 2>&1 && return 0
        sleep 0.25
    done
    die "$what did not come up within ${limit} s (logs: $D/log/)"
}

stop_pidfile() {  # stop_pidfile NAME PIDFILE: SIGTERM, then SIGKILL after 20 s
    local name=$1 f=$2 pid
    pid=$(pid_of "$f") || { rm -f "$f"; return 0; }
    kill -TERM "$pid"
    for ((i = 0; i < 80; i++)); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
    if kill -0 "$pid" 2>/dev/null; then
        say "$name (pid $pid) ignored SIGTERM for 20 s, sending SIGKILL"
        kill -KILL "$pid" 2>/dev/null || true
    fi
    rm -f "$f"
    say "stopped $name (pid $pid)"
}

# ---------------------------------------------------------------------------------------------
start_munge() {
    mkdir -p "$D/munge" && chmod 700 "$D/munge"
    [[ -s $D/munge/munge.key ]] || mungekey --create --keyfile="$D/munge/munge.key"
    chmod 400 "$D/munge/munge.key"
    if pid_of "$D/munge/munged.pid" >/dev/null; then return 0; fi
    munged --force --socket="$MUNGE_SOCKET" --key-file="$D/munge/munge.key" \
        --pid-file="$D/munge/munged.pid" --log-file="$D/log/munged.log" --seed-file="$D/munge/munged.seed"
    wait_for 10 munged test -S "$MUNGE_SOCKET"
    say "munged running (socket $MUNGE_SOCKET)"
}

sql() { mariadb --socket="$DB_SOCKET" -u root "$@"; }

start_mariadb() {
    if [[ ! -d $D/mysql/mysql ]]; then
        mkdir -p "$D/mysql"
        mariadb-install-db --user=root --datadir="$D/mysql" --auth-root-authentication-method=socket \
            --skip-test-db >"$D/log/mariadb-install.log" 2>&1 || die "mariadb-install-db failed, see $D/log/mariadb-install.log"
    fi
    if ! pid_of "$D/run/mariadbd.pid" >/dev/null; then
        # slurmdbd's recommended InnoDB settings (buffer pool, lock wait timeout)
        nohup mariadbd --no-defaults --user=root --datadir="$D/mysql" --socket="$DB_SOCKET" \
            --port=$((PORT + 3)) --bind-address=127.0.0.1 --skip-name-resolve \
            --pid-file="$D/run/mariadbd.pid" --log-error="$D/log/mariadb.log" \
            --innodb-buffer-pool-size=256M --innodb-log-file-size=64M --innodb-lock-wait-timeout=900 \
            >/dev/null 2>&1 &
        wait_for 60 MariaDB sql -e "SELECT 1"
    fi
    if [[ ! -s $D/etc/db.pass ]]; then
        (umask 077 && head -c 18 /dev/urandom | base64 | tr -d '/+=' >"$D/etc/db.pass")
    fi
    local pass; pass=$(<"$D/etc/db.pass")
    sql -e "CREATE DATABASE IF NOT EXISTS slurm_acct_db;
            CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY '$pass';
            ALTER USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$pass';
            GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';"
    say "MariaDB running (127.0.0.1:$((PORT + 3)), socket $DB_SOCKET)"
}

write_slurmdbd_conf() {
    (umask 077 && cat >"$D/etc/slurmdbd.conf" <<EOF
# written by scripts/slurm_local.sh
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCKET
DbdHost=localhost
DbdAddr=127.0.0.1
DbdPort=$((PORT + 2))
SlurmUser=root
LogFile=$D/log/slurmdbd.log
PidFile=$D/run/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$((PORT + 3))
StorageUser=slurm
StoragePass=$(<"$D/etc/db.pass")
StorageLoc=slurm_acct_db
EOF
    )
}

start_slurmdbd() {
    write_slurmdbd_conf
    if ! pid_of "$D/run/slurmdbd.pid" >/dev/null; then
        slurmdbd
        wait_for 60 slurmdbd sacctmgr -n list cluster
    fi
    say "slurmdbd running (127.0.0.1:$((PORT + 2)))"
}

register_accounting() {
    # the cluster, one account, and root in it (sacctmgr -i: no questions; errors = already there)
    sacctmgr -i add cluster "$CLUSTER" >/dev/null 2>&1 || true
    sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER" Description="wear-test pipeline" Organization=local >/dev/null 2>&1 || true
    sacctmgr -i add user root Account="$ACCOUNT" Cluster="$CLUSTER" >/dev/null 2>&1 || true
    sacctmgr -n -P list association cluster="$CLUSTER" user=root format=account | grep -qx "$ACCOUNT" \
        || die "could not register account $ACCOUNT for root in slurmdbd (see $D/log/slurmdbd.log)"
}

write_slurm_conf() {
    local host node mem_total mem
    host=$(hostname -s)
    # what slurmd sees on this machine (CPUs, sockets, cores, threads); memory: 3/4 of it by default
    node=$(slurmd -C | head -1 | sed -E 's/ RealMemory=[0-9]+//')
    mem_total=$(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo)
    mem=${WEAR_SLURM_MEM_MB:-$((mem_total * 3 / 4))}
    cat >"$SLURM_CONF" <<EOF
# written by scripts/slurm_local.sh ($1)
ClusterName=$CLUSTER
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCKET
CredType=cred/munge
StateSaveLocation=$D/spool/ctld
SlurmdSpoolDir=$D/spool/d
SlurmctldPidFile=$D/run/slurmctld.pid
SlurmdPidFile=$D/run/slurmd.pid
SlurmctldLogFile=$D/log/slurmctld.log
SlurmdLogFile=$D/log/slurmd.log
MpiDefault=none
SwitchType=switch/none
$(memory_limit_conf)
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=task=1
# finished jobs stay visible to squeue for 5 min (the profile's status polling relies on it)
MinJobAge=300
KillWait=10
OverTimeLimit=0
InactiveLimit=0
JobCompType=jobcomp/none
MailProg=/bin/true
EOF
    if [[ $1 == accounting ]]; then
        cat >>"$SLURM_CONF" <<EOF
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=$((PORT + 2))
# the munge socket for talking to slurmdbd (else the default /run/munge one)
AccountingStoragePass=$MUNGE_SOCKET
# sacct shows the job comment (the executor plugin writes the rule and wildcards there)
AccountingStoreFlags=job_comment
EOF
    else
        echo "AccountingStorageType=accounting_storage/none" >>"$SLURM_CONF"
    fi
    cat >>"$SLURM_CONF" <<EOF
$node RealMemory=$mem NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=$PARTITION Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
}

memory_limit_mode() {
    local m=${WEAR_SLURM_MEMORY_LIMIT:-auto}
    if [[ $m == auto ]]; then
        if [[ -f /sys/fs/cgroup/memory/memory.limit_in_bytes && -f /sys/fs/cgroup/freezer/cgroup.procs ]]; then
            m=cgroup
        else
            m=poll
        fi
    fi
    echo "$m"
}

memory_limit_conf() {  # prints the slurm.conf lines of the memory limit (writes cgroup.conf)
    if [[ $(memory_limit_mode) == cgroup ]]; then
        printf '%s\n' "# written by scripts/slurm_local.sh" CgroupPlugin=cgroup/v1 CgroupMountpoint=/sys/fs/cgroup \
            ConstrainRAMSpace=yes ConstrainSwapSpace=yes AllowedSwapSpace=0 ConstrainCores=no \
            ConstrainDevices=no >"$D/etc/cgroup.conf"
        printf '%s\n' "# memory: cgroup v1 (the kernel's OOM killer ends a job over its --mem)" \
            ProctrackType=proctrack/cgroup TaskPlugin=task/cgroup
    else
        rm -f "$D/etc/cgroup.conf"
        printf '%s\n' "# memory: the accounting poller kills a step over its --mem (checked every second)" \
            ProctrackType=proctrack/linuxproc TaskPlugin=task/none JobAcctGatherParams=OverMemoryKill
    fi
}

node_idle() { sinfo -h -N -o %t | grep -Eqx 'idle|mix|alloc'; }

start_slurm() {
    local mode=$1
    if ! pid_of "$D/run/slurmctld.pid" >/dev/null; then
        slurmctld
        wait_for 30 slurmctld scontrol ping
    fi
    if ! pid_of "$D/run/slurmd.pid" >/dev/null; then
        slurmd
    fi
    if ! (wait_for 30 "node $(hostname -s)" node_idle) 2>/dev/null; then
        scontrol update nodename="$(hostname -s)" state=resume >/dev/null 2>&1 || true
        wait_for 30 "node $(hostname -s) (sinfo: $(sinfo -h -N -o '%t %E'))" node_idle
    fi
    say "slurmctld and slurmd running, cluster $CLUSTER, partition $PARTITION ($mode)"
}

running_mode() {  # the mode of a running cluster, if any
    pid_of "$D/run/slurmctld.pid" >/dev/null && [[ -s $D/mode ]] && cat "$D/mode"
}

# ---------------------------------------------------------------------------------------------
cmd_install() {
    need_root
    command -v apt-get >/dev/null || die "needs apt-get (Debian/Ubuntu); elsewhere install SLURM, munge${ACCOUNTING:+, slurmdbd and MariaDB} yourself"
    local pkgs=("${PACKAGES[@]}")
    [[ -n $ACCOUNTING ]] && pkgs+=("${PACKAGES_ACCOUNTING[@]}")
    if dpkg-query -W -f='${Status}\n' "${pkgs[@]}" 2>/dev/null | grep -vq "install ok installed" \
        || [[ $(dpkg-query -W -f='${Status}\n' "${pkgs[@]}" 2>/dev/null | wc -l) -lt ${#pkgs[@]} ]]; then
        apt-get update -q
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q "${pkgs[@]}"
    fi
    say "installed: ${pkgs[*]}"
}

cmd_start() {
    need_root
    local mode=plain
    [[ -n $ACCOUNTING ]] && mode=accounting
    local cmds=(munged mungekey slurmctld slurmd sbatch squeue sinfo scontrol)
    [[ -n $ACCOUNTING ]] && cmds+=(slurmdbd sacctmgr mariadbd mariadb mariadb-install-db)
    need_commands "${cmds[@]}"
    if [[ -e /etc/slurm/slurm.conf && $(readlink /etc/slurm/slurm.conf) != "$SLURM_CONF" ]]; then
        die "/etc/slurm/slurm.conf exists and is not ours: this host has a SLURM configuration of its own; not starting"
    fi
    local current
    current=$(running_mode || true)
    if [[ $current == "$mode" ]] && node_idle; then
        say "already running ($mode)"
        cmd_env
        return 0
    fi
    [[ -n $current ]] && { say "running as '$current', restarting as '$mode'"; stop_daemons; }
    mkdir -p "$D"/{etc,log,run,spool/ctld,spool/d}
    start_munge
    write_slurm_conf "$mode"
    if [[ $mode == accounting ]]; then
        start_mariadb
        start_slurmdbd
        register_accounting
    fi
    echo "$mode" >"$D/mode"
    # Client commands inside the jobs must find this cluster without SLURM_CONF: the executor
    # plugin's job step drops SLURM_* variables before its inner srun. So the default path points
    # here while the cluster runs (removed by `stop`).
    mkdir -p /etc/slurm
    ln -sfn "$SLURM_CONF" /etc/slurm/slurm.conf
    start_slurm "$mode"
    cmd_env
}

stop_daemons() {
    if pid_of "$D/run/slurmctld.pid" >/dev/null; then
        local jobs
        jobs=$(squeue -h -o %i 2>/dev/null || true)
        if [[ -n $jobs ]]; then
            say "cancelling jobs: $(echo $jobs)"
            scancel $jobs 2>/dev/null || true
            sleep 2
        fi
    fi
    stop_pidfile slurmd "$D/run/slurmd.pid"
    stop_pidfile slurmctld "$D/run/slurmctld.pid"
    stop_pidfile slurmdbd "$D/run/slurmdbd.pid"
    stop_pidfile mariadbd "$D/run/mariadbd.pid"
}

cmd_stop() {
    need_root
    [[ -d $D ]] || { say "nothing to stop ($D does not exist)"; return 0; }
    stop_daemons
    stop_pidfile munged "$D/munge/munged.pid"
    if [[ $(readlink /etc/slurm/slurm.conf 2>/dev/null) == "$SLURM_CONF" ]]; then rm -f /etc/slurm/slurm.conf; fi
    rm -f "$D/mode"
    if [[ -n $PURGE ]]; then
        rm -rf "$D"
        say "removed $D"
    fi
}

cmd_status() {
    local name f pid
    for name in munged:munge/munged.pid mariadbd:run/mariadbd.pid slurmdbd:run/slurmdbd.pid \
        slurmctld:run/slurmctld.pid slurmd:run/slurmd.pid; do
        f=$D/${name#*:}
        if pid=$(pid_of "$f"); then echo "${name%%:*}: running (pid $pid)"; else echo "${name%%:*}: not running"; fi
    done
    if pid_of "$D/run/slurmctld.pid" >/dev/null; then
        echo "mode: $(cat "$D/mode" 2>/dev/null)"
        sinfo
    fi
}

cmd_env() {
    echo "export SLURM_CONF=$SLURM_CONF"
}

ACCOUNTING=""
PURGE=""
cmd=${1:-}
shift || true
for arg in "$@"; do
    case $arg in
        --accounting) ACCOUNTING=1 ;;
        --purge) PURGE=1 ;;
        *) die "unknown option $arg" ;;
    esac
done
case $cmd in
    install) cmd_install ;;
    start) cmd_start ;;
    stop) cmd_stop ;;
    status) cmd_status ;;
    env) cmd_env ;;
    *) sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
esac
