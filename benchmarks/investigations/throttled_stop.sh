#!/bin/bash
# A fleet stopping while its CEDDP is behind: do the robots' final reports arrive, and is every
# sample delivered or counted lost? (issue 17: "final reports must arrive, at any load")
#
#   bash benchmarks/investigations/throttled_stop.sh [CHECKOUT] [WORKDIR]
#
# Runs `python -m arpz.perf fleet --robots 50 --topics 8 --rate 100 --processes 4 --duration 30`
# from CHECKOUT (default: this one; give another worktree for a baseline) and, from 8 s into the
# load until 8 s after the robots are told to stop, stops the CEDDP process 60 ms of every 100 ms
# (SIGSTOP/SIGCONT): an overloaded server, with QoS control off (as `perf fleet` runs it), so
# nothing lowers the robots' rates and its backlog grows to seconds. Prints the fleet's lines,
# how many final reports the CEDDP's summary has and what it counted lost, and the robots'
# shutdown warnings.
set -u
dir=${1:-$(cd "$(dirname "$0")/../.." && pwd)}
wd=${2:-/tmp/arpz-throttled-stop}
rm -rf "$wd"
mkdir -p "$(dirname "$wd")"
(cd "$dir" && PYTHONPATH=$dir python -m arpz.perf fleet --robots 50 --topics 8 --rate 100 \
    --processes 4 --duration 30 --workdir "$wd" > "$wd.log" 2>&1 &)
for _ in $(seq 1 600); do grep -q " [89]\.[0-9]/30 s" "$wd.log" 2>/dev/null && break; sleep 0.5; done
ceddp=$(pgrep -f "arpz.ceddp --config $wd" | head -1)
if [ -z "$ceddp" ]; then
    echo "throttled_stop: no CEDDP process for $wd (see $wd.log)" >&2
    exit 1
fi
echo "throttling the CEDDP (pid $ceddp) from $(date +%T)"
throttle() { kill -STOP "$ceddp"; sleep 0.06; kill -CONT "$ceddp"; sleep 0.04; }
trap 'kill -CONT "$ceddp" 2>/dev/null' EXIT  # never leave it stopped
give_up=$((SECONDS + 120))
while ! grep -q "stopping the robots" "$wd.log" && [ $SECONDS -lt $give_up ]; do throttle; done
end=$((SECONDS + 8))
while [ $SECONDS -lt $end ]; do throttle; done
kill -CONT "$ceddp"
echo "released at $(date +%T), 8 s after the robots were told to stop"
for _ in $(seq 1 300); do grep -q "^reconciled\|^FAILED" "$wd.log" && break; sleep 1; done
grep -E "^CEDDP|^FAILED|^reconciled" "$wd.log" | cut -c1-330
python -c "
import json
robots = json.load(open('$wd/ceddp0.json'))['robots']
final = sum(1 for row in robots.values() if row.get('final_stats'))
lost = sum(row.get('lost', 0) for row in robots.values())
print(f'final reports {final} of {len(robots)}, lost {lost}')
"
grep -h "unacknowledged\|not acknowledged" "$wd"/worker*.log | sed 's/[0-9.]\+ s/N s/g' | sort | uniq -c
