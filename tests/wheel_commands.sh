#!/usr/bin/env bash
# The package as a user installs it: in VENV, which holds lolgps_torch installed from a wheel
# (not the checkout), the `lolgps` command, run outside the checkout, trains a two-condition
# stream, evaluates it, and sweeps 2 seeds of it on Ray (each cell then evaluated) and again
# (the finished cells skipped). Run by .ci/run:  tests/wheel_commands.sh VENV
set -euo pipefail
venv=$(cd "$1" && pwd)
root=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"
export PATH="$venv/bin:$PATH" LOLGPS_WORKERS=1 OMP_NUM_THREADS=1
package=$(python -c 'import lolgps_torch; print(lolgps_torch.__file__)')
if [[ "$package" == "$root/lolgps_torch/"* ]]; then
    echo "lolgps_torch was imported from the checkout ($package), not from the wheel" >&2
    exit 1
fi
urdf=$(python -c 'from lolgps_torch.gym_env import DEFAULT_URDF; print(DEFAULT_URDF)')
echo '[[0.0, 0.0], [0.01, -0.01]]' > conditions.json
small=(--max-iterations 7 --success-phases 1 --distill-steps 100 --repairs 0)
lolgps run --urdf "$urdf" --conditions conditions.json "${small[@]}" --out run > run.log
tail -n 1 run.log
lolgps evaluate --run run --workers 1 --positions conditions.json > /dev/null
test -f run/eval.json
sweep=(--seeds 0-1 --urdf "$urdf" --conditions conditions.json --out sweep --num-cpus 2
       --evaluate --evaluate-args="--positions $work/conditions.json" -- "${small[@]}")
lolgps sweep "${sweep[@]}"
[[ -f sweep/lolgps-kuka_peg-paper-seed1/eval.json && -f sweep/summary.md ]]
again=$(lolgps sweep "${sweep[@]}")
[[ "$again" == *"2 cells in $work/sweep: 2 finished before (skipped)"* ]]
echo "the installed lolgps command trained, evaluated and swept (package: $package)"
