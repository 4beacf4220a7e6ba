#!/usr/bin/env bash
# The workflow on a real SLURM cluster: a one-node cluster on this machine, the tiny synthetic
# scene of tests/workflow/test_workflow.py run through workflow/profiles/slurm (every job via sbatch), the
# same target run locally, and the two parameter stores compared.
#
#   sudo scripts/slurm_localhost.sh [--repo DIR] [--workdir DIR] [--python PY] [--keep-cluster]
#   sudo scripts/slurm_localhost.sh --stop [--workdir DIR]     # stop a cluster left by --keep-cluster
#
# --repo       the checkout to test (default: the one this script lives in)
# --workdir    scratch folder (default /tmp/sellip-slurm-test); wiped and rebuilt on every run
# --python     the Python whose snakemake runs the workflow (default: $PYTHON, else the repo's
#              .venv/bin/python, else python3); the SLURM executor plugin is pip-installed into it
# --target     output to build and compare, relative to the workdir (default: the parameter store
#              of iteration 0's first fit, results/tiny/iter/0/{fit,params}.zarr, whichever exists)
# --keep-cluster  leave slurmctld/slurmd (and munged, when this script started it) running
# SELLIP_JAX_CACHE (environment)  the XLA compilation cache both runs use (default: the tiny config's own)
#
# Needs root (apt-get install slurm-wlm munge on first use, daemons without systemd) on
# Debian/Ubuntu. Idempotent: daemons left by an earlier run are stopped first, the work folder is
# rebuilt. pytest wrapper: SELLIP_SLURM_TEST=1 pytest tests/workflow/test_slurm.py. docs/hpc.md has more.
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
WORK=/tmp/sellip-slurm-test
PY=${PYTHON:-}
TARGET=""
KEEP=0
STOP_ONLY=0
while [ $# -gt 0 ]; do
  case "$1" in
    --repo) REPO=$(cd "$2" && pwd); shift 2 ;;
    --workdir) WORK=$2; shift 2 ;;
    --python) PY=$2; shift 2 ;;
    --target) TARGET=$2; shift 2 ;;
    --keep-cluster) KEEP=1; shift ;;
    --stop) STOP_ONLY=1; shift ;;
    -h|--help) sed -n '2,22p' "$0"; exit 0 ;;
    *) echo "slurm_localhost: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
if [ -z "$PY" ]; then
  if [ -x "$REPO/.venv/bin/python" ]; then PY=$REPO/.venv/bin/python; else PY=$(command -v python3); fi
fi
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
CLUSTER=$WORK/cluster                 # state, spool, logs, pid files
# slurmd's step sockets live in the spool folder (spool/NODE_JOB.STEP, ~20 characters): a Unix socket path is at
# most 108 bytes, and past it every job launch fails and waits "launch failed requeued held" for ever.
if [ $(( ${#CLUSTER} + 30 )) -gt 108 ]; then
  echo "slurm_localhost: --workdir $WORK is too long for slurmd's sockets (its spool path must stay under 108" \
       "bytes): give a shorter one, e.g. /tmp/sellip-slurm-test" >&2
  exit 2
fi
# The config must be at the default path: the plugin's job step drops SLURM_* variables
# (SLURM_CONF included) before its nested srun. A slurm.conf this script did not write is left alone.
CONF=/etc/slurm/slurm.conf
MARKER="# Written by scripts/slurm_localhost.sh"
unset SLURM_CONF
NODE=$(hostname -s)
PARTITION=sellip
CPUS=2
T0=$SECONDS
declare -A TIMES=()

say() { echo "== slurm_localhost [$((SECONDS - T0)) s] $*"; }
fail() { echo "slurm_localhost: FAILED: $*" >&2; exit 1; }

pid_alive() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

stop_cluster() {
  # Stop only the daemons this script started (their pid files live in $CLUSTER).
  local stopped=0
  if pid_alive "$CLUSTER/slurmctld.pid" || pid_alive "$CLUSTER/slurmd.pid"; then
    scontrol shutdown >/dev/null 2>&1 || true
    for _ in $(seq 1 20); do
      pid_alive "$CLUSTER/slurmctld.pid" || pid_alive "$CLUSTER/slurmd.pid" || break
      sleep 0.5
    done
    for f in slurmctld slurmd; do
      if pid_alive "$CLUSTER/$f.pid"; then kill "$(cat "$CLUSTER/$f.pid")" 2>/dev/null || true; fi
    done
    stopped=1
  fi
  if pid_alive "$CLUSTER/munged.pid"; then
    kill "$(cat "$CLUSTER/munged.pid")" 2>/dev/null || true
    rm -f "$CLUSTER/munged.pid"
    stopped=1
  fi
  if [ "$KEEP" = 0 ] && [ -f "$CONF" ] && head -1 "$CONF" | grep -qF "$MARKER"; then rm -f "$CONF"; fi
  [ "$stopped" = 1 ] && echo "== slurm_localhost: stopped the local SLURM cluster (and munged if it was ours)"
  return 0
}

if [ "$STOP_ONLY" = 1 ]; then stop_cluster; exit 0; fi
[ "$(id -u)" = 0 ] || fail "run as root: it installs slurm-wlm/munge and starts slurmctld/slurmd"
[ -f "$REPO/Snakefile" ] || fail "$REPO is not a sellip checkout (no Snakefile)"
[ -f "$REPO/workflow/profiles/slurm/config.yaml" ] || fail "no workflow/profiles/slurm/config.yaml in $REPO"
export PYTHONPATH="$REPO/src${PYTHONPATH:+:$PYTHONPATH}"   # this checkout's sellip, in jobs too
"$PY" -c 'import snakemake, sellip' 2>/dev/null || fail "$PY cannot import snakemake and sellip (make install, or --python)"
if [ "$KEEP" = 0 ]; then trap stop_cluster EXIT; fi

# 1. Install SLURM, munge and the executor plugin (once).
t=$SECONDS
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null; then
  command -v apt-get >/dev/null || fail "slurm-wlm and munge are missing and there is no apt-get"
  say "installing slurm-wlm and munge (apt-get)"
  apt-get update -qq || fail "apt-get update"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null || fail "apt-get install slurm-wlm munge"
fi
if ! "$PY" -c 'import snakemake_executor_plugin_slurm' 2>/dev/null; then
  say "installing snakemake-executor-plugin-slurm into $("$PY" -c 'import sys; print(sys.prefix)')"
  "$PY" -m pip install --quiet snakemake-executor-plugin-slurm || fail "pip install snakemake-executor-plugin-slurm"
fi
TIMES[install]=$((SECONDS - t))
say "$(dpkg-query -W -f='slurm-wlm ${Version}' slurm-wlm 2>/dev/null || echo slurm), snakemake-executor-plugin-slurm $("$PY" -c 'import importlib.metadata as m; print(m.version("snakemake-executor-plugin-slurm"))')"

# 2. A one-node cluster on localhost: munge, slurmctld, slurmd (no systemd, no slurmdbd).
t=$SECONDS
stop_cluster
rm -rf "$WORK"/{cluster,slurm,local,profile,tiny.yaml}
mkdir -p "$CLUSTER"/{state,spool,log}
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
  [ -s /etc/munge/munge.key ] || { mungekey --create 2>/dev/null || dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none; }
  chown munge:munge /etc/munge/munge.key; chmod 0400 /etc/munge/munge.key
  mkdir -p /run/munge /var/log/munge /var/lib/munge; chown munge:munge /run/munge /var/log/munge /var/lib/munge
  runuser -u munge -- /usr/sbin/munged --pid-file=/run/munge/munged.pid || fail "munged did not start"
  cp /run/munge/munged.pid "$CLUSTER/munged.pid"
  for _ in $(seq 1 20); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.25; done
  munge -n | unmunge >/dev/null || fail "munge does not work (see /var/log/munge/munged.log)"
fi
if [ -f "$CONF" ] && ! head -1 "$CONF" | grep -qF "$MARKER"; then
  fail "$CONF exists and was not written by this script: this machine has its own SLURM set-up; not touching it"
fi
mkdir -p "$(dirname "$CONF")"
MEM_MB=$(awk '/MemTotal/ {print int($2 / 1024) - 512}' /proc/meminfo)
cat > "$CONF" <<EOF
$MARKER: a one-node test cluster on $NODE (removed when it stops).
ClusterName=sellip-localhost
SlurmctldHost=$NODE(127.0.0.1)
SlurmctldPort=16817
SlurmdPort=16818
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$CLUSTER/state
SlurmdSpoolDir=$CLUSTER/spool
SlurmctldPidFile=$CLUSTER/slurmctld.pid
SlurmdPidFile=$CLUSTER/slurmd.pid
SlurmctldLogFile=$CLUSTER/log/slurmctld.log
SlurmdLogFile=$CLUSTER/log/slurmd.log
# No cgroups in a container: track processes by parent id, no task binding.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
MpiDefault=none
# No slurmdbd: sacct cannot see jobs, so the executor polls squeue, which keeps finished jobs
# for MinJobAge seconds; the plugin needs MinJobAge >= 3 x its first status-check delay.
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$CLUSTER/log/jobcomp.txt
MinJobAge=3600
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
# Use the CPUs/memory below even where the hardware reports a different layout.
SlurmdParameters=config_overrides
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=$PARTITION Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
slurmctld -c || fail "slurmctld did not start (see $CLUSTER/log/slurmctld.log)"
slurmd -N "$NODE" || fail "slurmd did not start (see $CLUSTER/log/slurmd.log)"
state=""
for _ in $(seq 1 60); do
  state=$(sinfo -h -n "$NODE" -o %t 2>/dev/null || true)
  [ "$state" = idle ] && break
  sleep 0.5
done
if [ "$state" != idle ]; then
  scontrol show node "$NODE" >&2 || true
  tail -20 "$CLUSTER/log/slurmctld.log" "$CLUSTER/log/slurmd.log" >&2 || true
  fail "node $NODE is '${state:-unreachable}', not idle"
fi
TIMES[cluster]=$((SECONDS - t))
say "cluster up: node $NODE, $CPUS CPUs, $MEM_MB MB, partition $PARTITION"

# 3. The tiny scene's config (tests/workflow/test_workflow.py) and the slurm profile with its two
#    cluster-specific values filled in and its resources clamped to this node.
"$PY" - "$REPO" "$WORK" "$PARTITION" "$CPUS" "$MEM_MB" <<'EOF'
import shutil, sys
from pathlib import Path
import yaml
repo, work, partition, cpus, mem = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
sys.path[:0] = [str(repo / "tests" / "workflow"), str(repo / "tests")]
from test_workflow import tiny_config
import os
for run in ("slurm", "local"):
    (work / run).mkdir(parents=True, exist_ok=True)
    config = tiny_config(work / run)
    if os.environ.get("SELLIP_JAX_CACHE"):  # the caller's XLA cache (the test suite's session cache)
        config["fit"]["compilation_cache"] = os.environ["SELLIP_JAX_CACHE"]
    (work / run / "tiny.yaml").write_text(yaml.safe_dump(config))
profile = yaml.safe_load((repo / "workflow/profiles/slurm/config.yaml").read_text())
defaults = profile.setdefault("default-resources", {})
defaults["slurm_partition"] = partition
defaults.pop("slurm_account", None)            # no accounts here (--slurm-no-account)
def clamp(resources):
    if "mem_mb" in resources:
        resources["mem_mb"] = min(int(resources["mem_mb"]), mem)
    if "cpus_per_task" in resources:
        resources["cpus_per_task"] = min(int(resources["cpus_per_task"]), cpus)
clamp(defaults)
for resources in (profile.get("set-resources") or {}).values():
    clamp(resources)
profile["set-threads"] = {rule: min(int(n), cpus) for rule, n in (profile.get("set-threads") or {}).items()}
profile["set-scatter"] = {"fit": tiny_config(work)["fit"]["shards"]}   # the local run's shards
profile.pop("software-deployment-method", None)   # no conda here: jobs use the Python of snakemake
profile.pop("conda-prefix", None)
(work / "profile").mkdir(exist_ok=True)
(work / "profile" / "config.yaml").write_text(yaml.safe_dump(profile, sort_keys=False))
EOF

export PATH="$(dirname "$PY"):$PATH"                       # its `sellip` and `snakemake`
smk() {  # smk RUN ARGS...: snakemake on the repo's workflow in $WORK/RUN with the tiny config
  local run=$1; shift
  "$PY" -m snakemake --snakefile "$REPO/Snakefile" --directory "$WORK/$run" \
    --configfile "$REPO/config/config.yaml" "$WORK/$run/tiny.yaml" "$@"
}
if [ -z "$TARGET" ]; then
  for candidate in results/tiny/iter/0/fit.zarr results/tiny/iter/0/params.zarr; do
    if smk local -n --quiet --cores 1 "$candidate" >/dev/null 2>&1; then TARGET=$candidate; break; fi
  done
  [ -n "$TARGET" ] || fail "neither results/tiny/iter/0/fit.zarr nor .../params.zarr is a target of this workflow (--target)"
fi
say "target: $TARGET"

# 4. The SLURM run: every job through sbatch (the plugin polls squeue; no accounts here).
t=$SECONDS
if ! smk slurm --workflow-profile "$WORK/profile" --slurm-no-account --slurm-status-command squeue \
      --slurm-init-seconds-before-status-checks 2 --slurm-keep-successful-logs "$TARGET" \
      > "$WORK/slurm.log" 2>&1; then
  tail -40 "$WORK/slurm.log" >&2
  echo "--- slurmctld.log (last lines)" >&2; tail -10 "$CLUSTER/log/slurmctld.log" >&2 || true
  fail "the SLURM run failed: $WORK/slurm.log, job logs in $WORK/slurm/.snakemake/slurm_logs and $WORK/slurm/results/tiny/logs"
fi
TIMES[slurm_run]=$((SECONDS - t))
# Every job went through sbatch and completed: the plugin's submissions vs slurmctld's job log.
"$PY" - "$WORK/slurm.log" "$CLUSTER/log/jobcomp.txt" <<'EOF' || fail "the jobs did not all go through SLURM (see above)"
import re, sys
log = open(sys.argv[1]).read()
submitted = re.findall(r"has been submitted with SLURM jobid (\d+)", log)
done = re.findall(r"(\d+) of (\d+) steps \(100%\) done", log)
completed = {}
for line in open(sys.argv[2]):
    fields = dict(f.split("=", 1) for f in line.split() if "=" in f)
    completed[fields.get("JobId")] = fields.get("JobState")
if not submitted:
    sys.exit("no job was submitted with sbatch")
if not done or int(done[-1][1]) != len(submitted):
    sys.exit(f"{len(submitted)} sbatch submissions, but snakemake reports {done[-1] if done else 'no'} steps done")
bad = {j: completed.get(j, "missing") for j in submitted if completed.get(j) != "COMPLETED"}
if bad:
    sys.exit(f"jobs not COMPLETED in slurmctld's job completion log: {bad}")
print(f"== {len(submitted)} jobs submitted with sbatch, all COMPLETED in the job completion log (SLURM job ids {submitted[0]}..{submitted[-1]})")
EOF
grep -oE "rule [a-z_]+:" "$WORK/slurm.log" | sort | uniq -c | sed 's/^/   /'

# 5. The same target locally (workflow/profiles/default, 2 cores), from the SLURM run's capture,
#    HDR images, cameras and initial mesh: init_mesh is not bit-reproducible from run to run
#    (multithreaded Poisson; 2407, 2413 and 2414 vertices in three runs of the tiny scene), so the
#    local run redoes what follows it (observations, fit shards, gather) on the same inputs.
t=$SECONDS
rm -rf "$WORK/local"
cp -a "$WORK/slurm" "$WORK/local"
rm -rf "$WORK/local/.snakemake/"{slurm_logs,log,locks,incomplete} "$WORK/local/$TARGET"
if ! smk local --workflow-profile "$REPO/workflow/profiles/default" --cores 2 "$TARGET" > "$WORK/local.log" 2>&1; then
  tail -40 "$WORK/local.log" >&2
  fail "the local run failed: $WORK/local.log"
fi
grep -oE "rule [a-z_]+:" "$WORK/local.log" | sort | uniq -c | sed 's/^/   local: /'
TIMES[local_run]=$((SECONDS - t))

# 6. Compare the two parameter stores, array by array.
"$PY" - "$WORK/slurm/$TARGET" "$WORK/local/$TARGET" <<'EOF' || fail "the SLURM and local parameter stores differ (see above)"
import sys
import numpy as np
import zarr
a, b = zarr.open_group(sys.argv[1], mode="r"), zarr.open_group(sys.argv[2], mode="r")
def arrays(group, prefix=""):
    out = {}
    for name, item in group.members():
        if isinstance(item, zarr.Group):
            out.update(arrays(item, f"{prefix}{name}/"))
        else:
            out[prefix + name] = item[...]
    return out
x, y = arrays(a), arrays(b)
if set(x) != set(y):
    sys.exit(f"different arrays: SLURM {sorted(x)}, local {sorted(y)}")
problems, identical = [], 0
for name in sorted(x):
    u, v = x[name], y[name]
    if u.shape != v.shape or u.dtype != v.dtype:
        problems.append(f"{name}: {u.dtype}{u.shape} vs {v.dtype}{v.shape}")
    elif np.array_equal(u, v, equal_nan=np.issubdtype(u.dtype, np.floating)):
        identical += 1
    elif np.issubdtype(u.dtype, np.floating) and np.allclose(u, v, rtol=1e-5, atol=1e-6, equal_nan=True):
        print(f"   {name}: equal to float32 tolerance (max |diff| {np.nanmax(np.abs(u - v)):.3g})")
    else:
        diff = np.nanmax(np.abs(u.astype(float) - v.astype(float))) if u.size else 0
        problems.append(f"{name}: differs (max |diff| {diff:.3g}, {np.sum(u != v)} of {u.size} elements)")
for p in problems:
    print("   " + p)
if problems:
    sys.exit(1)
print(f"== parameter stores agree: {len(x)} arrays, {identical} bit-identical")
EOF

TOTAL=$((SECONDS - T0))
say "PASSED: install ${TIMES[install]} s, cluster start ${TIMES[cluster]} s, SLURM run ${TIMES[slurm_run]} s, local run ${TIMES[local_run]} s, total $TOTAL s"
