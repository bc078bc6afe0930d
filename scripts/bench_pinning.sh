#!/usr/bin/env bash
# Two simulator benchmarks at once, as two batch workers run: unpinned (each process may use every core, and
# XLA's CPU pool has a thread per core) against each pinned to a core of its own (as `quasisim batch` pins its
# workers), alternating, ROUNDS times; then one process alone, unpinned and pinned. Prints the 60-frame
# forward + backward and forward times (s) of each process. Needs 2 cores.
# Usage: scripts/bench_pinning.sh [ROUNDS]   (from the repository root, after `make setup`)
set -euo pipefail
rounds=${1:-2}
q=".venv/bin/quasisim"
out=$(mktemp -d)
sim() { "$@" "$q" bench sim --study-clips "" --dt-study 20 --json 2>/dev/null; }
times() { python3 -c 'import json,sys
for f in sys.argv[1:]:
    d = json.load(open(f)); print("%.2f / %.2f" % (d["rollout60_fwd_bwd_s"], d["rollout60_forward_s"]), end="  ")
print()' "$@"; }
echo "layout: fwd+bwd / fwd (s) per process"
for r in $(seq "$rounds"); do
  sim env > "$out/a.json" & sim env > "$out/b.json" & wait
  echo -n "round $r, 2 processes, unpinned: "; times "$out/a.json" "$out/b.json"
  sim taskset -c 0 > "$out/a.json" & sim taskset -c 1 > "$out/b.json" & wait
  echo -n "round $r, 2 processes, pinned:   "; times "$out/a.json" "$out/b.json"
  sim env > "$out/a.json"; echo -n "round $r, alone, unpinned:         "; times "$out/a.json"
  sim taskset -c 0 > "$out/a.json"; echo -n "round $r, alone, pinned:           "; times "$out/a.json"
done
rm -rf "$out"
