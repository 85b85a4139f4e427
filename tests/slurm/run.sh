#!/usr/bin/env bash
# The Slurm job-array test of `nimbus datagen`: a single-node Slurm on localhost runs
# each generator (global, p2p) as a job array of 4 shards; the merged shards must be
# byte-identical to a one-machine run, a resubmitted (complete) array must change no
# chunk, and one task resubmitted after losing a chunk must remake just that chunk.
#
#   tests/slurm/run.sh [NIMBUS]        # NIMBUS: a built binary, default target/ci/nimbus
#
# Needs root and Debian's `slurm-wlm` and `munge` (apt-get install slurm-wlm munge).
# Without them it prints SKIP and exits 0; in CI (CI set) it fails instead.
#
# Everything it makes lies in one fresh temporary directory (`mktemp -d`, under
# $TMPDIR or /tmp): a private munge key, socket and munged; slurm.conf (SLURM_CONF
# points to it, so /etc/slurm is neither read nor written); slurmctld's state, slurmd's
# spool, the logs, the data sets. Nothing under /etc is touched. The daemons listen on
# 127.0.0.1 on the first free pair of ports from 16817 (SLURM_TEST_PORT to change it),
# so a second run, or a real Slurm on the same machine, does not collide. The daemons
# it started are stopped on exit; the directory is removed after a pass and kept after
# a failure (or with KEEP=1) for its logs.
set -euo pipefail

nimbus_arg=${1:-target/ci/nimbus}
export PATH=$PATH:/usr/sbin:/sbin

skip_or_fail() {
  if [ -n "${CI:-}" ]; then
    echo "slurm test: FAIL: cannot run: $*" >&2
    exit 1
  fi
  echo "slurm test: SKIP: $* (CI would fail here)"
  exit 0
}

[ "$(id -u)" = 0 ] || skip_or_fail "needs root to run munged, slurmctld and slurmd"
missing=()
for c in munged slurmctld slurmd sbatch sinfo srun scontrol; do
  command -v "$c" >/dev/null 2>&1 || missing+=("$c")
done
[ ${#missing[@]} -eq 0 ] ||
  skip_or_fail "missing ${missing[*]} (apt-get install slurm-wlm munge)"
if [ ! -x "$nimbus_arg" ]; then
  echo "slurm test: FAIL: no nimbus binary at $nimbus_arg" >&2
  exit 1
fi
nimbus_bin=$(realpath "$nimbus_arg")

# A job inherits the submitting environment; drop any Slurm job of our own caller.
while read -r v; do unset "$v"; done < <(compgen -e | grep '^SLURM_' || true)

t0=$EPOCHREALTIME
elapsed() { awk -v a="$1" -v b="$EPOCHREALTIME" 'BEGIN { printf "%.1f s", b - a }'; }

work=$(mktemp -d "${TMPDIR:-/tmp}/nimbus-slurm.XXXXXX")
chmod 755 "$work"  # munged wants every directory above its socket searchable by all
pids=()
failures=0
results=()

cleanup() {
  local rc=$?
  local i
  [ ${#pids[@]} -lt 3 ] || timeout 10 scancel --user="$(id -un)" 2>/dev/null || true
  for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
    kill "${pids[i]}" 2>/dev/null || true
    wait "${pids[i]}" 2>/dev/null || true
  done
  if [ "$rc" = 0 ] && [ "$failures" = 0 ] && [ -z "${KEEP:-}" ]; then
    rm -rf "$work"
  else
    echo "slurm test: logs and data kept in $work"
  fi
}
trap cleanup EXIT

die() {
  echo "slurm test: FAIL: $*" >&2
  local f
  for f in "$work"/log/*.log; do
    [ -f "$f" ] || continue
    echo "--- last lines of $f" >&2
    tail -n 20 "$f" >&2
  done
  exit 1
}

mkdir -p "$work"/{munge,etc,state,spool,log,bin}
ln -s "$nimbus_bin" "$work/bin/nimbus"
export PATH=$work/bin:$PATH

# --- munge: a private key, socket and daemon -----------------------------------------
key=$work/munge/munge.key
if command -v mungekey >/dev/null 2>&1; then
  mungekey --create --keyfile="$key"
else
  dd if=/dev/urandom of="$key" bs=1024 count=1 status=none
fi
chmod 0400 "$key"
sock=$work/munge/munge.socket
munged --foreground --key-file="$key" --socket="$sock" --pid-file="$work/munge/munged.pid" \
  --log-file="$work/log/munged.log" --seed-file="$work/munge/munged.seed" \
  >"$work/log/munged.out" 2>&1 &
pids+=($!)

# --- slurm.conf for one node -----------------------------------------------------------
port_busy() { (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
port=${SLURM_TEST_PORT:-16817}
while port_busy "$port" || port_busy $((port + 1)); do
  port=$((port + 2))
  [ "$port" -lt 16917 ] || die "no free port pair from ${SLURM_TEST_PORT:-16817}"
done
cpus=$(nproc)
mem=$(awk '/^MemTotal:/ { m = int($2 / 1024) - 512; print (m > 1 ? m : 1) }' /proc/meminfo)
export SLURM_CONF=$work/etc/slurm.conf
cat >"$SLURM_CONF" <<EOF
# Single-node Slurm for tests/slurm/run.sh: slurmctld and slurmd on localhost, as root.
ClusterName=nimbus-test
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$port
SlurmdPort=$((port + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$sock
StateSaveLocation=$work/state
SlurmdSpoolDir=$work/spool
SlurmctldPidFile=$work/slurmctld.pid
SlurmdPidFile=$work/slurmd.pid
SlurmctldLogFile=$work/log/slurmctld.log
SlurmdLogFile=$work/log/slurmd.log
# No cgroups in a container: track processes by their parent, bind nothing.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
# The node is what this file says, whatever hwloc finds.
SlurmdParameters=config_overrides
ReturnToService=2
# Start queued array tasks as soon as CPUs free up (default: up to 3 s later), and
# keep finished jobs 4 s, so that sbatch --wait polls every 2 s (not 2 s, then 8 s).
SchedulerParameters=batch_sched_delay=0
MinJobAge=4
# A merge whose array failed is cancelled rather than left pending.
DependencyParameters=kill_invalid_depend
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=test Nodes=localhost Default=YES MaxTime=INFINITE State=UP
EOF

for _ in $(seq 50); do [ -S "$sock" ] && break; sleep 0.1; done
[ -S "$sock" ] || die "munged did not start"

slurmctld -D >"$work/log/slurmctld.out" 2>&1 &
pids+=($!)
slurmd -D -N localhost >"$work/log/slurmd.out" 2>&1 &
pids+=($!)
state=
for _ in $(seq 150); do
  state=$(sinfo -h -n localhost -o %t 2>/dev/null || true)
  [ "$state" = idle ] && break
  sleep 0.2
done
[ "$state" = idle ] || die "node localhost not idle after 30 s (sinfo: '${state}')"
[ "$(timeout 60 srun -N1 -n1 hostname)" = "$(hostname)" ] || die "srun hostname failed"
echo "slurm test: single-node Slurm up ($cpus CPUs, ports $port-$((port + 1))) in $(elapsed "$t0"); work dir $work"

# --- the checks -----------------------------------------------------------------------
record() {  # record NAME OK [DETAIL]
  if [ "$2" = 0 ]; then
    results+=("PASS  $1")
  else
    results+=("FAIL  $1${3:+: $3}")
    failures=$((failures + 1))
  fi
  echo "slurm test: ${results[-1]}"
}

# The job script, in the form docs/global-model.md and docs/point-to-point.md show:
# array task i makes shard i/4.
write_script() {  # write_script FILE OUT GENERATOR-ARGS..
  local file=$1 out=$2 job
  job=$(basename "$file" .sbatch)
  shift 2
  cat >"$file" <<EOF
#!/bin/bash
#SBATCH --job-name=$job
#SBATCH --array=0-3
#SBATCH --cpus-per-task=1
#SBATCH --time=00:10:00
#SBATCH --output=logs/%x-%A_%a.out
set -euo pipefail
nimbus datagen $* \\
    --shard "\$SLURM_ARRAY_TASK_ID/4" --threads "\$SLURM_CPUS_PER_TASK" \\
    --quiet --out "$out/shard-\$SLURM_ARRAY_TASK_ID"
EOF
}

snapshot() {  # every chunk of the shards with its inode, size and mtime
  find "$1" -path '*/chunks/*' -type f -printf '%P %i %s %T@\n' | sort
}

same_manifest() {  # the same but for the run time
  diff <(grep -v '"seconds"' "$1") <(grep -v '"seconds"' "$2") >/dev/null
}

run_generator() {  # run_generator NAME GENERATOR-ARGS..
  local name=$1
  shift
  local t=$EPOCHREALTIME
  local ref=$work/ref/$name shards=$work/shards/$name merged=$work/merged/$name
  local script=$work/datagen-$name.sbatch
  local f ok

  echo "slurm test: $name: one machine"
  nimbus datagen "$@" --quiet --out "$ref" >"$work/log/ref-$name.out" 2>&1
  record "$name: one-machine reference" $? "see $work/log/ref-$name.out"

  # As the docs submit it: the array, then the merge as a job that waits for it.
  write_script "$script" "shards/$name" "$@"
  echo "slurm test: $name: sbatch $script, then the merge with --dependency=afterok"
  local jid
  ok=0
  jid=$(sbatch --parsable "$script" 2>"$work/log/sbatch-$name.out") || ok=$?
  record "$name: job array of 4 shards submitted" $ok "see $work/log/sbatch-$name.out"
  ok=0
  timeout 300 sbatch --wait --dependency="afterok:$jid" --output=logs/merge-%j.out \
    --wrap "nimbus datagen merge shards/$name/shard-* --out merged/$name" \
    >>"$work/log/sbatch-$name.out" 2>&1 || ok=$?
  # A merge cancelled because a task failed also leaves sbatch --wait with 0.
  [ "$ok" != 0 ] || grep -q '"complete": true' "$merged/manifest.json" 2>/dev/null || ok=1
  record "$name: all 4 tasks done, then the merge job" $ok "see $work/logs/"

  for f in features.npy targets.npy; do
    ok=0
    cmp "$ref/$f" "$merged/$f" || ok=$?
    record "$name: $f byte-identical to one machine" $ok
  done
  ok=0
  same_manifest "$ref/manifest.json" "$merged/manifest.json" || ok=$?
  record "$name: manifest the same (but for the run time)" $ok

  # Resume: the array again, over complete shards, keeps every chunk file as it is
  # (a rewritten chunk would be a new file: a temporary one renamed over it).
  local before after
  before=$(snapshot "$shards")
  ok=0
  timeout 300 sbatch --wait "$script" >>"$work/log/sbatch-$name.out" 2>&1 || ok=$?
  after=$(snapshot "$shards")
  [ "$ok" = 0 ] && [ "$before" = "$after" ] || ok=1
  record "$name: resubmitted array is a no-op (all $(grep -c chunk- <<<"$before") chunks kept)" $ok

  # One task again after it lost a chunk: it remakes that chunk and keeps the rest.
  local lost
  lost=$(find "$shards/shard-1/chunks" -name 'chunk-*' | sort | tail -n 1)
  rm -f "$lost"
  lost=${lost#"$shards"/}
  before=$(grep -vF "$lost " <<<"$before")
  ok=0
  timeout 300 sbatch --wait --array=1 "$script" >>"$work/log/sbatch-$name.out" 2>&1 || ok=$?
  after=$(snapshot "$shards")
  [ "$ok" = 0 ] && [ -f "$shards/$lost" ] && [ "$before" = "$(grep -vF "$lost " <<<"$after")" ] || ok=1
  record "$name: task 1 resubmitted alone remakes its lost ${lost##*/}, keeps the rest" $ok
  ok=0
  nimbus datagen merge "$shards"/shard-* --out "$merged-again" >>"$work/log/merge-$name.out" 2>&1 &&
    cmp "$ref/features.npy" "$merged-again/features.npy" &&
    cmp "$ref/targets.npy" "$merged-again/targets.npy" || ok=1
  record "$name: merged again, still byte-identical" $ok
  echo "slurm test: $name done in $(elapsed "$t")"
}

mkdir -p "$work/logs"
cd "$work"
set +e  # from here on each step records its result; the summary decides the exit
run_generator global global --points 64 --sigma 1..20 --g 0..0.9 --n-dirs 16 \
  --max-rel-error 0.3 --chunk-size 8 --seed 7
run_generator p2p p2p --cloud scene-a --resolution 32 --rho 10 --points 12 --rotations 2 \
  --max-rel-error 0.5 --chunk-size 3 --seed 4
set -e

echo
echo "slurm test summary ($(elapsed "$t0")):"
printf '  %s\n' "${results[@]}"
if [ "$failures" -gt 0 ]; then
  echo "slurm test: FAIL ($failures of ${#results[@]} checks failed)"
  exit 1
fi
echo "slurm test: PASS (${#results[@]} checks)"
