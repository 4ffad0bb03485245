#!/usr/bin/env bash
# Fuzzes the plant's message decoding and scenario parsing with libFuzzer
# (clang, ASan + UBSan) for a set time per target, one target at a time.
#
#   bash scripts/fuzz.sh                 # 60 s per target
#   bash scripts/fuzz.sh 300             # 300 s per target
#   bash scripts/fuzz.sh 60 fuzz_scenario
#   FUZZ_RUNS=10000000 bash scripts/fuzz.sh 0 fuzz_policy   # a number of inputs instead
#
# Targets: fuzz_messages (the plant's command handling), fuzz_scenario, one
# per message decoder (fuzz_valve_command, fuzz_plant_control, fuzz_plant_state,
# fuzz_policy, fuzz_policy_ack: bounded decoding, cpp/plant/lcm/wire.h, tests/fuzz/wire_harness.h;
# fuzz_policy_v2: cpp/policy/push_wire.h),
# fuzz_signed (the keyed receivers' signature check, then decoding) and
# fuzz_py_wire (the Python receivers' decoding and check: the links, ftc.replay
# and the push tool; atheris, installed into .venv when missing).
#
# Builds into build-fuzz/ (-DFTC_FUZZ=ON), never part of the default build or
# test command. Seeds: tests/fuzz/corpus/<target>/ (committed); the growing
# corpus is kept in build-fuzz/corpus/, crash inputs in build-fuzz/crashes/.
# Exits non-zero if any target found a crash.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
seconds="${1:-60}"
shift || true
targets=("$@")
[ ${#targets[@]} -eq 0 ] && targets=(fuzz_messages fuzz_scenario fuzz_valve_command \
  fuzz_plant_control fuzz_plant_state fuzz_policy fuzz_policy_ack fuzz_policy_v2 fuzz_signed fuzz_py_wire)
limit=(-max_total_time="$seconds")
[ -n "${FUZZ_RUNS:-}" ] && limit=(-runs="$FUZZ_RUNS")

# clang and its libFuzzer/sanitizer runtime: only fuzzing needs them.
if ! command -v clang++ >/dev/null || ! ls /usr/lib/llvm-*/lib/clang/*/lib/linux/libclang_rt.fuzzer-x86_64.a >/dev/null 2>&1 \
    || ! ls /usr/lib/llvm-*/lib/libomp.so >/dev/null 2>&1; then
  # SUNDIALS' CMake package needs OpenMP for clang: libomp.
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get install -y -q clang libclang-rt-14-dev libomp-14-dev
fi

# LCM's CMake package comes with the pip wheel in .venv (scripts/setup.sh).
[ -x .venv/bin/python ] || bash scripts/setup.sh
lcm_cmake="$(.venv/bin/python -c 'import lcm, os; print(os.path.join(os.path.dirname(os.path.dirname(lcm.__file__)), "lib", "lcm", "cmake"))')"
cmake -S . -B build-fuzz -Dlcm_DIR="$lcm_cmake" -DFTC_FUZZ=ON -DFTC_BUILD_TESTS=OFF -DFTC_BUILD_PYTHON=OFF \
  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_C_COMPILER=clang -DCMAKE_CXX_COMPILER=clang++ >/dev/null
native=()
for t in "${targets[@]}"; do [[ "$t" == fuzz_py_* ]] || native+=("$t"); done
[ ${#native[@]} -gt 0 ] && cmake --build build-fuzz -j2 --target "${native[@]}"
if [[ " ${targets[*]}" == *" fuzz_py_"* ]] && ! .venv/bin/python -c "import atheris" 2>/dev/null; then
  .venv/bin/python -m pip install -q atheris
fi

status=0
for t in "${targets[@]}"; do
  seeds="tests/fuzz/corpus/${t#fuzz_}"
  corpus="build-fuzz/corpus/${t#fuzz_}"
  crashes="build-fuzz/crashes/$t/"
  mkdir -p "$corpus" "$crashes"
  dict=()
  [ -f "tests/fuzz/${t#fuzz_}.dict" ] && dict=(-dict="tests/fuzz/${t#fuzz_}.dict")
  echo "== $t: ${limit[*]}, seeds $seeds"
  # -jobs=1: the machine has 2 cores and other work on it.
  run=(./build-fuzz/"$t")
  [[ "$t" == fuzz_py_* ]] && run=(.venv/bin/python "tests/fuzz/$t.py")
  if ! "${run[@]}" "$corpus" "$seeds" "${dict[@]}" -rss_limit_mb=512 "${limit[@]}" \
      -artifact_prefix="$crashes" -print_final_stats=1 2>"build-fuzz/$t.log"; then
    echo "$t: FOUND A CRASH (see build-fuzz/$t.log, inputs in $crashes)"
    status=1
  fi
  grep -E "^stat::number_of_executed_units|^stat::average_exec_per_sec|^stat::peak_rss_mb|Done [0-9]+ runs" "build-fuzz/$t.log" || true
  tail -n 1 "build-fuzz/$t.log"
done
exit $status
