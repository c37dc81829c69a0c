#!/usr/bin/env bash
# A real single-node SLURM cluster on this machine, for tests and for trying the templates.
#
#   slurm/local_cluster.sh start    # install slurm-wlm + munge when missing, start munged, slurmctld, slurmd
#   slurm/local_cluster.sh status   # sinfo + squeue
#   slurm/local_cluster.sh env      # prints: export SLURM_CONF=...
#   slurm/local_cluster.sh stop     # stops the three daemons (by the pids they wrote)
#
# Everything (slurm.conf, munge key and socket, state, spool, logs, pid files) lives in
# ${ERMRL_SLURM_DIR:-/tmp/ermrl-slurm}; nothing is written to /etc. Clients find the cluster
# through SLURM_CONF:  eval "$(slurm/local_cluster.sh env)"; sbatch ...
#
# Must run as root (SlurmUser=root, jobs run as root). `start` is idempotent: it does nothing but
# print the env line when the cluster already answers. The node advertises
# ${ERMRL_SLURM_CPUS:-max(nproc, 4)} CPUs (SlurmdParameters=config_overrides), so a 4-task array
# runs at once even on a 2-core machine.
set -euo pipefail

DIR=${ERMRL_SLURM_DIR:-/tmp/ermrl-slurm}
CONF=$DIR/slurm.conf
NODE=$(hostname -s)
CTLD_PORT=${ERMRL_SLURMCTLD_PORT:-16817}
SLURMD_PORT=${ERMRL_SLURMD_PORT:-16818}

log() { echo "local_cluster: $*" >&2; }
die() { log "error: $*"; exit 1; }

pid_alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

install_packages() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null \
     && command -v sbatch >/dev/null && command -v munged >/dev/null; then
    return
  fi
  command -v apt-get >/dev/null || die "slurm-wlm/munge are missing and apt-get is not available"
  log "installing slurm-wlm and munge from Debian (apt-get)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq >&2
  apt-get install -y -qq --no-install-recommends slurm-wlm munge >&2
}

write_conf() {
  local cpus mem_mb
  cpus=${ERMRL_SLURM_CPUS:-$(nproc)}
  if [ -z "${ERMRL_SLURM_CPUS:-}" ] && [ "$cpus" -lt 4 ]; then cpus=4; fi
  mem_mb=$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)
  cat >"$CONF" <<EOF
# Written by slurm/local_cluster.sh: a single-node test cluster; everything under $DIR.
ClusterName=ermrl-local
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
AuthType=auth/munge
AuthInfo=socket=$DIR/munge/munge.socket
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/run/slurmctld.pid
SlurmdPidFile=$DIR/run/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SchedulerType=sched/backfill
MpiDefault=none
SwitchType=switch/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
ReturnToService=2
SlurmdParameters=config_overrides
SlurmctldTimeout=30
SlurmdTimeout=60
InactiveLimit=0
KillWait=10
MinJobAge=600
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
}

start_munged() {
  if pid_alive "$DIR/run/munged.pid"; then return; fi
  if [ ! -s "$DIR/munge/munge.key" ]; then
    dd if=/dev/urandom of="$DIR/munge/munge.key" bs=1024 count=1 status=none
    chmod 400 "$DIR/munge/munge.key"
  fi
  munged --force \
    --key-file="$DIR/munge/munge.key" \
    --socket="$DIR/munge/munge.socket" \
    --pid-file="$DIR/run/munged.pid" \
    --log-file="$DIR/log/munged.log" \
    --seed-file="$DIR/munge/munged.seed"
}

cluster_answers() {
  SLURM_CONF=$CONF timeout 5 scontrol ping 2>/dev/null | grep -q "is UP"
}

node_state() {
  SLURM_CONF=$CONF timeout 5 sinfo -h -n "$NODE" -o %t 2>/dev/null | head -n1 | tr -d '*~#!%$@^-'
}

start() {
  [ "$(id -u)" -eq 0 ] || die "run as root (SlurmUser=root; jobs run as root)"
  if [ -f "$CONF" ] && pid_alive "$DIR/run/slurmctld.pid" && pid_alive "$DIR/run/slurmd.pid" \
     && cluster_answers; then
    log "already running ($CONF)"
    echo "export SLURM_CONF=$CONF"
    return
  fi
  install_packages
  mkdir -p "$DIR"/{state,spool,log,run,munge}
  chmod 700 "$DIR/munge"
  write_conf
  start_munged
  pid_alive "$DIR/run/slurmctld.pid" || slurmctld -f "$CONF"
  pid_alive "$DIR/run/slurmd.pid" || slurmd -f "$CONF" -N "$NODE"
  local state=""
  for _ in $(seq 60); do
    state=$(node_state || true)
    case "$state" in
      idle|mix|alloc|comp) break ;;
      down|drain|drng|fail|unk|"") ;;
    esac
    if [ "$state" = down ] || [ "$state" = drain ]; then
      SLURM_CONF=$CONF scontrol update NodeName="$NODE" State=RESUME >/dev/null 2>&1 || true
    fi
    sleep 0.5
  done
  case "$state" in
    idle|mix|alloc|comp) ;;
    *) die "node $NODE is '${state:-unknown}' after 30 s; see $DIR/log/slurmctld.log and slurmd.log" ;;
  esac
  log "up: node $NODE ($state), conf $CONF, logs $DIR/log"
  echo "export SLURM_CONF=$CONF"
}

stop() {
  local name pidfile pid
  for name in slurmd slurmctld munged; do
    pidfile=$DIR/run/$name.pid
    if pid_alive "$pidfile"; then
      pid=$(cat "$pidfile")
      kill "$pid" 2>/dev/null || true
      for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
      kill -0 "$pid" 2>/dev/null && kill -9 "$pid" 2>/dev/null || true
      log "stopped $name ($pid)"
    fi
    rm -f "$pidfile"
  done
}

status() {
  [ -f "$CONF" ] || die "not started ($CONF missing)"
  SLURM_CONF=$CONF sinfo
  SLURM_CONF=$CONF squeue
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  restart) stop; start ;;
  status) status ;;
  env) echo "export SLURM_CONF=$CONF" ;;
  *) echo "usage: $0 start|stop|restart|status|env" >&2; exit 2 ;;
esac
