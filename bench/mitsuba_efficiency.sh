#!/usr/bin/env bash
# Nimbus against Mitsuba 3 at equal variance on the three kinds of cloud (a dense
# homogeneous blob, the lobed cumulus, a modeler cloud with interior noise), Mitsuba
# with its default Russian roulette and with roulette off. One JSON line per run.
# Usage: bench/mitsuba_efficiency.sh NIMBUS [SPP] [OUT_DIR]
set -euo pipefail
nimbus=${1:?usage: bench/mitsuba_efficiency.sh NIMBUS [SPP] [OUT_DIR]}
spp=${2:-256}
out=${3:-/tmp/nimbus_mitsuba}
here=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$out"
for cloud in sphere cumulus scene-a; do
  dir="$out/$cloud"
  "$nimbus" bench render --cloud "$cloud" --spp "$spp" --mitsuba-dir "$dir" | tail -1 > "$dir.nimbus.json"
  for rr in 5 off; do
    echo "== $cloud, Mitsuba rr_depth $rr" >&2
    python3 "$here/mitsuba_compare.py" "$dir" --spp "$spp" --threads 2 --rr-depth "$rr" --repeats 8 \
      | tail -1 | sed "s/^{/{\"cloud\": \"$cloud\", /"
  done
done
