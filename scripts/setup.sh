#!/usr/bin/env bash
# Sets up a fresh machine for this project, idempotently:
#   1. Debian packages (SUNDIALS, Eigen, CLI11, GoogleTest, toml++, CMake, a C++ compiler);
#   2. a virtual environment .venv with the pinned Python dependencies
#      (requirements.txt, then the interoperability ones in requirements-extra.txt) and the
#      ftc package installed in editable mode;
#   3. CMake configure and build into build/ (plant, tests, Python bindings,
#      generated LCM types).
# Each step is skipped quickly when it is already done. Safe to re-run.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

apt_packages=(libsundials-dev libeigen3-dev libcli11-dev libgtest-dev libtomlplusplus-dev
              cmake g++ make iproute2)
missing=()
for p in "${apt_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing Debian packages: ${missing[*]}"
  sudo_cmd=""; [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

# lcm-logger records thousands of lockstep messages a second; a recorder
# descheduled on a busy machine needs a large UDP receive buffer or the kernel
# drops datagrams (counted in /proc/net/snmp RcvbufErrors). LCM's own advice.
want_rmem=67108864
if [ "$(cat /proc/sys/net/core/rmem_max 2>/dev/null || echo 0)" -lt "$want_rmem" ]; then
  if [ "$(id -u)" -eq 0 ] && sysctl -qw net.core.rmem_max="$want_rmem" 2>/dev/null; then
    echo "setup: raised net.core.rmem_max to $want_rmem for lcm-logger"
  else
    echo "setup: note: could not raise net.core.rmem_max (lcm-logger may drop messages under load)"
  fi
fi

python_bin="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$python_bin" -m venv .venv
fi
stamp=.venv/.requirements.sha
want="$(cat requirements.txt requirements-extra.txt pyproject.toml | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: installing Python dependencies into .venv"
  quiet_pip() {  # this machine's pip config names local mirrors that may be absent: not errors
    .venv/bin/pip "$@" 2>&1 | { grep -v "^WARNING: Location .* is ignored" || true; }
    return "${PIPESTATUS[0]}"
  }
  quiet_pip install -q --upgrade pip
  quiet_pip install -q -r requirements.txt
  quiet_pip install -q -r requirements-extra.txt
  quiet_pip install -q --no-deps --no-build-isolation -e .
  echo "$want" > "$stamp"
fi

lcm_cmake="$(.venv/bin/python -c 'import lcm, os; print(os.path.join(os.path.dirname(os.path.dirname(lcm.__file__)), "lib", "lcm", "cmake"))')"
pybind_cmake="$(.venv/bin/python -m pybind11 --cmakedir)"
if [ ! -f build/Makefile ]; then
  cmake -S . -B build -DCMAKE_BUILD_TYPE=Release \
    -Dlcm_DIR="$lcm_cmake" -Dpybind11_DIR="$pybind_cmake" \
    -DPython_EXECUTABLE="$root/.venv/bin/python" >/dev/null
fi
if ! cmake --build build -j"$(nproc)" > build/build.log 2>&1; then
  cat build/build.log >&2
  echo "setup: build failed (full log: build/build.log)" >&2
  exit 1
fi
echo "setup: ready (build/plant, .venv)"
