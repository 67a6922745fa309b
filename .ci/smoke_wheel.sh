#!/usr/bin/env bash
# Smoke test of a built wheel as a user gets it: installs WHEEL (without extras, so no
# matplotlib) into a new venv outside the source tree and runs the package from a folder
# outside the tree. Usage: bash .ci/smoke_wheel.sh dist/nanostage-*.whl
set -uo pipefail
[ $# -eq 1 ] && [ -f "$1" ] || { echo "usage: $0 WHEEL" >&2; exit 2; }
WHEEL=$(cd "$(dirname "$1")" && pwd)/$(basename "$1")
PY=${PYTHON:-python3}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
unset NANOSTAGE_EMPS_MAT PYTHONPATH VIRTUAL_ENV

"$PY" -m venv "$WORK/venv" || exit 1
"$WORK/venv/bin/python" -m pip install -q --upgrade pip || exit 1
"$WORK/venv/bin/python" -m pip install -q "$WHEEL" || { echo "smoke: wheel install failed"; exit 1; }
export PATH="$WORK/venv/bin:$PATH"
mkdir "$WORK/run" && cd "$WORK/run" || exit 1

passed=0
failed=0
check() { # check NAME CONDITION...: run CONDITION, count and print the result
    local name=$1
    shift
    if "$@"; then
        passed=$((passed + 1))
        echo "smoke ok:   $name"
    else
        failed=$((failed + 1))
        echo "smoke FAIL: $name"
        sed 's/^/    | /' out.txt err.txt 2>/dev/null | head -20
    fi
}
run() { # run CMD...: stdout to out.txt, stderr to err.txt, exit code to $code
    "$@" >out.txt 2>err.txt
    code=$?
}
no_traceback() { ! grep -q "Traceback" out.txt err.txt; }

# 1. The package is imported from the venv (not the tree) and simulates a step.
run python - <<'EOF'
import pathlib, sys
import nanostage
assert "site-packages" in pathlib.Path(nanostage.__file__).parts, nanostage.__file__
tr = nanostage.simulate_step(nanostage.presets.seed(1e-3), 1e-3, duration_s=0.5)
err = abs(int(tr.encoder_counts[-1]) - int(tr.reference_counts[-1]))
print(f"nanostage {nanostage.__version__} from {nanostage.__file__}: final error {err} counts")
sys.exit(0 if err <= 1 else 1)
EOF
check "import nanostage and simulate a 1 mm step" test "$code" -eq 0

# 2. The console script.
run nanostage --help
check "nanostage --help" eval '[ "$code" -eq 0 ] && grep -q "reproduce" out.txt && grep -q "iso230" out.txt'

# 3. ISO 230-2 evaluation of a tiny CSV (5 targets, 5 runs each way).
python - <<'EOF'
import random
random.seed(1)
with open("tiny.csv", "w") as f:
    f.write("target_m,direction,run,actual_m\n")
    for run in range(1, 6):
        for direction, targets in (("+", range(5)), ("-", reversed(range(5)))):
            for i in targets:
                t = i * 2e-3
                f.write(f"{t!r},{direction},{run},{t + random.gauss(0, 1e-7)!r}\n")
EOF
run nanostage iso230 tiny.csv --out iso
check "nanostage iso230 tiny.csv" eval '[ "$code" -eq 0 ] && [ -s iso/iso230_2.json ] && [ -s iso/iso230_2.md ] && no_traceback'

# 4. emps without data: a one-line usage error, exit 2, no traceback.
run nanostage emps --out emps
check "nanostage emps without --mat: one-line error, exit 2" eval '[ "$code" -eq 2 ] && [ "$(wc -l <err.txt)" -eq 1 ] && grep -q "nanostage emps:" err.txt && no_traceback'

# 5. reproduce without matplotlib: the table and summary.json, and one line on the figures.
run python -c 'import importlib.util, sys; sys.exit(importlib.util.find_spec("matplotlib") is not None)'
check "matplotlib is not installed with the bare wheel" test "$code" -eq 0
run nanostage reproduce --out rep
check "nanostage reproduce without matplotlib" eval '[ "$code" -eq 0 ] && [ -s rep/summary.json ] && [ ! -e rep/steps.png ] && grep -q "| " out.txt && [ "$(wc -l <err.txt)" -eq 1 ] && grep -qF "pip install \"nanostage[plot]\"" err.txt && no_traceback'

# 6. The presets are read from the model files the wheel ships (nanostage/model_files):
# the seed in 1, the EMPS here.
run nanostage model export emps_asymmetric --out emps.model.toml
check "nanostage model export emps_asymmetric (a shipped preset file)" eval '[ "$code" -eq 0 ] && grep -q "force_drive" emps.model.toml && no_traceback'

echo "smoke: $passed passed, $failed failed"
[ "$failed" -eq 0 ]
