#!/usr/bin/env bash
# Regenerates the synthetic records shipped in data/ (made by vsidgen itself; no third-party data).
# ATTAS short-period model (specs/attas_sp.yaml) with parameters near the textbook output-error
# estimates, turbulence-level process noise and sensor-level measurement noise.
set -euo pipefail
cd "$(dirname "$0")/.."
PARAMS=(--param Z0=-0.009 --param ZAL=-0.483 --param ZQ=0.104 --param ZDE=0.676
        --param M0=0.475 --param MAL=-4.93 --param MQ=-2.01 --param MDE=-7.21)
NOISE=(--process-std alpha=0.005 --process-std q=0.01
       --measurement-std alpha=0.0017 --measurement-std q=0.0028)
vsidgen simulate specs/attas_sp.yaml --out data/attas_sp_synthetic.csv "${PARAMS[@]}" "${NOISE[@]}" \
  --input "de=const:value=0.04+3211:amplitude=0.02,start=2,unit=1" \
  --duration 25 --dt 0.04 --x0 alpha=0.037 --seed 1
vsidgen simulate specs/attas_sp.yaml --out data/attas_sp_synthetic_val.csv "${PARAMS[@]}" "${NOISE[@]}" \
  --input "de=const:value=0.04+doublet:amplitude=0.025,start=3,width=1.5" \
  --duration 25 --dt 0.04 --x0 alpha=0.037 --seed 2
