#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for trying `layerbvh sweep --cluster slurm` and for the
# tests: bash scripts/slurm_local.sh start|stop|status
#
# start: installs Debian's slurmctld, slurmd and munge if they are missing, writes a minimal
#   slurm.conf (one node: this machine, its cores and memory; partition `debug`) and a munge key
#   under $LAYERBVH_SLURM_DIR (default /tmp/layerbvh-slurm), starts munged (unless one runs),
#   slurmctld and slurmd as root, and waits until `sinfo` shows the node idle. It prints the line
#   to source: export SLURM_CONF=DIR/slurm.conf (sbatch, squeue and dask-jobqueue read it). It also
#   links that file as $XDG_CACHE_HOME/layerbvh/slurm/slurm.conf, which `layerbvh sweep --cluster
#   slurm` uses when SLURM_CONF is unset and no other controller answers: nothing to source.
# stop: ends exactly the processes start started (their pid files), nothing else, and removes the link.
# status: sinfo and squeue of that cluster.
# Needs root (the daemons run as root, packages come from apt) on a Debian-like system; refuses
# with one line otherwise.
set -euo pipefail
DIR=${LAYERBVH_SLURM_DIR:-/tmp/layerbvh-slurm}
CONF="$DIR/slurm.conf"
LINK="${XDG_CACHE_HOME:-$HOME/.cache}/layerbvh/slurm/slurm.conf"  # (the sweep's slurm.local_cluster_conf)
say() { printf 'slurm_local: %s\n' "$*" >&2; }

need_root() {
  if [ "$(id -u)" != 0 ]; then say "needs root (the SLURM daemons and munged run as root here); run it as root"; exit 2; fi
}

install_packages() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null \
      && command -v sbatch >/dev/null; then
    return
  fi
  if ! command -v apt-get >/dev/null; then
    say "slurmctld, slurmd and munge are missing and there is no apt-get to install them"; exit 2
  fi
  say "installing Debian packages slurmctld slurmd munge"
  apt-get update -qq >/dev/null
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends slurmctld slurmd munge >/dev/null
}

write_config() {
  local host cpus mem
  host=$(hostname -s)
  cpus=$(nproc --all)  # not `nproc`: the starting process may be pinned to fewer CPUs
  mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))  # MiB, leaving 1 GiB to the OS
  mkdir -p "$DIR/state" "$DIR/spool" "$DIR/log"
  # No cgroups, no accounting database: what a container or a laptop can run.
  cat > "$CONF" <<EOF
ClusterName=layerbvh
SlurmctldHost=$host
SlurmctldPort=${LAYERBVH_SLURMCTLD_PORT:-6817}
SlurmdPort=${LAYERBVH_SLURMD_PORT:-6818}
AuthType=auth/munge
SlurmUser=root
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/log/slurmctld.log
SlurmdLogFile=$DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MpiDefault=none
KillWait=5
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
}

start_munge() {
  if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    return  # a munged already answers (the system's, or ours from an earlier start)
  fi
  mkdir -p /etc/munge /run/munge /var/lib/munge /var/log/munge
  if [ ! -s /etc/munge/munge.key ]; then
    dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key 2>/dev/null
  fi
  chown -R munge:munge /etc/munge /run/munge /var/lib/munge /var/log/munge 2>/dev/null || true
  chmod 400 /etc/munge/munge.key
  munged --force --pid-file="$DIR/munged.pid" 2>/dev/null
  for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && return; sleep 0.1; done
  say "munged did not start (see /var/log/munge/munged.log)"; exit 1
}

alive() { local pid; pid=$(cat "$1" 2>/dev/null) && kill -0 "$pid" 2>/dev/null; }

up() { mkdir -p "$(dirname "$LINK")" && ln -sfn "$CONF" "$LINK"; echo "export SLURM_CONF=$CONF"; }

start() {
  need_root
  install_packages
  if alive "$DIR/slurmctld.pid" && alive "$DIR/slurmd.pid"; then
    say "already running"; up; return
  fi
  write_config
  start_munge
  # The daemons (and so the jobs) get every CPU, whatever this shell was pinned to.
  local all="0-$(( $(nproc --all) - 1 ))"
  taskset -c "$all" slurmctld -f "$CONF"
  taskset -c "$all" slurmd -f "$CONF"
  for _ in $(seq 100); do
    if SLURM_CONF=$CONF sinfo -h -o '%T' 2>/dev/null | grep -qx idle; then
      up; return
    fi
    sleep 0.2
  done
  say "the node did not come up idle within 20 s; logs in $DIR/log"; exit 1
}

stop() {
  local f
  for f in slurmd slurmctld munged; do
    if alive "$DIR/$f.pid"; then
      kill "$(cat "$DIR/$f.pid" 2>/dev/null)" 2>/dev/null || true
      for _ in $(seq 50); do alive "$DIR/$f.pid" || break; sleep 0.1; done
    fi
    rm -f "$DIR/$f.pid"
  done
  if [ "$(readlink "$LINK" 2>/dev/null)" = "$CONF" ]; then rm -f "$LINK"; fi
}

status() {
  if alive "$DIR/slurmctld.pid"; then SLURM_CONF=$CONF sinfo; SLURM_CONF=$CONF squeue; else say "not running"; exit 1; fi
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) status ;;
  *) say "usage: bash scripts/slurm_local.sh start|stop|status"; exit 2 ;;
esac
