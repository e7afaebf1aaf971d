#!/usr/bin/env bash
# Five ant MAML runs at once on the device machine (oracle seeds 1 2, UML-random seeds 0 1 2), 3 cores each,
# learning on DEVICE; SIGTERM after RUN_S seconds (each run saves after its iteration in flight); results to $OUT.
# Usage: DEVICE=cuda RUN_S=380 EXTRA="" bash docs/measurements/2026-12-04-h200/ant_maml_five_runs.sh
ENV=ant RUNS="oracle:1 oracle:2 random:0 random:1 random:2" ITERATIONS=300 EVERY=25 CORES=3 \
  exec bash "$(dirname "$0")/../../../scripts/device/maml_runs_at_once.sh"
