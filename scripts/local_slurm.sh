#!/usr/bin/env bash
# A real single-node SLURM cluster on this machine, for trying the workflow's SLURM path end to end.
#
#   scripts/local_slurm.sh start [--gpu]   write /etc/slurm/slurm.conf and start munged, slurmctld, slurmd
#   scripts/local_slurm.sh status          daemons, node state and queue
#   scripts/local_slurm.sh stop            stop the daemons (by the PIDs in their pid files)
#
# Needs Debian's slurm-wlm and munge (apt-get install -y slurm-wlm munge) and root (it writes
# /etc/slurm and starts daemons). No systemd: the daemons are started directly and daemonize.
# The node is this machine: its short host name, its CPUs and its memory (less 1 GiB). --gpu declares
# one fake GPU (gres.conf: File=/dev/null) so that GPU-requesting rules can be scheduled on a CPU node.
#
# Why the config lives at /etc/slurm/slurm.conf and not under SLURM_CONF: the SLURM executor's job step
# clears SLURM_* variables before its inner srun, so a config elsewhere is not found there.
# Accounting is off (no slurmdbd): use the plugin's `--slurm-status-command squeue`; with the default
# `sacct` status check the workflow waits forever without an error.
set -euo pipefail

CONF_DIR=/etc/slurm
RUN_DIR=/run/slurm
LOG_DIR=/var/log/slurm
STATE_DIR=/var/lib/slurm
PARTITION=local

die() { echo "local_slurm.sh: $*" >&2; exit 1; }

need_tools() {
    local missing=()
    for t in munged slurmctld slurmd sinfo squeue sbatch; do command -v "$t" >/dev/null || missing+=("$t"); done
    if ((${#missing[@]})); then
        die "not installed: ${missing[*]}. Install with: apt-get install -y slurm-wlm munge"
    fi
    [[ $(id -u) == 0 ]] || die "must run as root (writes $CONF_DIR and starts daemons)"
}

pid_alive() { [[ -f $1 ]] && kill -0 "$(cat "$1")" 2>/dev/null; }

write_conf() {
    local gpu=$1 host cpus mem gres_line=""
    host=$(hostname -s)
    cpus=$(nproc)
    mem=$(awk '/MemTotal/ {print int($2 / 1024) - 1024}' /proc/meminfo)
    mkdir -p "$CONF_DIR" "$RUN_DIR" "$LOG_DIR" "$STATE_DIR/slurmctld" "$STATE_DIR/slurmd"
    chown slurm:slurm "$LOG_DIR" "$STATE_DIR/slurmctld" "$RUN_DIR"
    if [[ $gpu == 1 ]]; then
        gres_line="Gres=gpu:1"
        printf 'NodeName=%s Name=gpu File=/dev/null Count=1\n' "$host" > "$CONF_DIR/gres.conf"
    else
        rm -f "$CONF_DIR/gres.conf"
    fi
    cat > "$CONF_DIR/slurm.conf" <<EOF
# written by wast3d scripts/local_slurm.sh: a single-node cluster on $host
ClusterName=wast3d-local
SlurmctldHost=$host(127.0.0.1)
SlurmUser=slurm
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
GresTypes=gpu
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
ReturnToService=2
StateSaveLocation=$STATE_DIR/slurmctld
SlurmdSpoolDir=$STATE_DIR/slurmd
SlurmctldPidFile=$RUN_DIR/slurmctld.pid
SlurmdPidFile=$RUN_DIR/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem $gres_line State=UNKNOWN
PartitionName=$PARTITION Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
    echo "wrote $CONF_DIR/slurm.conf: node $host, $cpus CPUs, $mem MB${gres_line:+, $gres_line (fake, File=/dev/null)}"
}

start() {
    local gpu=0
    [[ ${1:-} == --gpu ]] && gpu=1
    need_tools
    if pid_alive "$RUN_DIR/slurmctld.pid"; then die "already running (scripts/local_slurm.sh stop first)"; fi
    write_conf "$gpu"
    mkdir -p /run/munge && chown munge:munge /run/munge && chmod 0755 /run/munge
    if ! pid_alive /run/munge/munged.pid; then
        runuser -u munge -- munged --force
    fi
    slurmctld
    slurmd
    # wait for the node to come up idle (the controller registers the node within a few seconds)
    for _ in $(seq 60); do
        if sinfo -h -N -o '%T' 2>/dev/null | grep -qx idle; then
            echo "local SLURM up: partition '$PARTITION'"
            sinfo -N -o '%N %P %C %m %G %T'
            return 0
        fi
        sleep 0.5
    done
    die "node did not become idle in 30 s; see $LOG_DIR/slurmctld.log and $LOG_DIR/slurmd.log"
}

stop() {
    local f pid
    for f in "$RUN_DIR/slurmd.pid" "$RUN_DIR/slurmctld.pid" /run/munge/munged.pid; do
        if pid_alive "$f"; then
            pid=$(cat "$f")  # read before the kill: the daemon removes its pid file as it exits
            kill "$pid"
            echo "stopped $(basename "$f" .pid) (pid $pid)"
        fi
    done
    # wait for them to exit, so that a following start finds the ports free
    for _ in $(seq 40); do
        pid_alive "$RUN_DIR/slurmd.pid" || pid_alive "$RUN_DIR/slurmctld.pid" || return 0
        sleep 0.25
    done
}

status() {
    local f rc=0
    for f in /run/munge/munged.pid "$RUN_DIR/slurmctld.pid" "$RUN_DIR/slurmd.pid"; do
        if pid_alive "$f"; then echo "$(basename "$f" .pid): running (pid $(cat "$f"))"
        else echo "$(basename "$f" .pid): not running"; rc=3; fi
    done
    if ((rc == 0)); then sinfo -N -o '%N %P %C %m %G %T'; squeue; fi
    return $rc
}

case ${1:-} in
    start) shift; start "$@" ;;
    stop) stop ;;
    status) status ;;
    *) echo "usage: $0 start [--gpu] | stop | status" >&2; exit 2 ;;
esac
