#!/usr/bin/env bash
# Sets up a fresh machine for this project, idempotently:
#   1. Debian packages (SUNDIALS, Eigen, CLI11, GoogleTest, toml++, CMake, a C++ compiler);
#   2. a virtual environment .venv with the pinned Python dependencies
#      (requirements.txt, then the interoperability ones in requirements-extra.txt) and the
#      checkout's python/ on its path (as an editable install would put it, without
#      building the C++ parts twice: `pip install .` builds them into the package);
#   3. SUNDIALS' CVODE built optimised from Debian's source into build/sundials
#      (Debian's library is built -O0; see below);
#   4. CMake configure and build into build/ (plant, tests, Python bindings,
#      generated LCM types).
# Each step is skipped quickly when it is already done. Safe to re-run.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

apt_packages=(libsundials-dev libeigen3-dev libcli11-dev libgtest-dev libtomlplusplus-dev libssl-dev
              cmake g++ make ccache iproute2 curl xz-utils)
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
  # byte-compiled afterwards on every core (pip compiles file by file: 85 s of
  # the install against 40 s without it here; compileall -j 0 takes 29 s). The
  # .pyc files must exist: with PYTHONDONTWRITEBYTECODE set (as on CI machines)
  # Python never writes them, and every process would compile torch's imports
  # again (1.5 s more per `import torch`, measured)
  quiet_pip install -q --no-compile --upgrade pip
  quiet_pip install -q --no-compile -r requirements.txt
  quiet_pip install -q --no-compile -r requirements-extra.txt
  quiet_pip uninstall -q -y ftc >/dev/null 2>&1 || true  # an install of the package itself
  # in the background while CVODE and the C++ build below run; the stamp is
  # written once it is done (a package's test data that is not Python makes
  # compileall exit 1: no error)
  purelib="$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
  ( .venv/bin/python -m compileall -q -j 0 "$purelib" >/dev/null 2>&1 || [ "$?" -eq 1 ] \
      || echo "setup: note: byte-compiling .venv failed; every Python start will be slower" >&2
  ) &
  compile_pid=$!
  stamp_after_compile="$want"
fi
# the lcm wheel, kept: tests/python/test_install.py installs it, with no index,
# into a fresh venv beside the package (whose plant finds liblcm there)
lcm_pin="$(grep -m1 '^lcm==' requirements.txt)"
ls .venv/wheelhouse/"lcm-${lcm_pin#lcm==}"-*.whl >/dev/null 2>&1 \
  || .venv/bin/pip download -q --no-deps "$lcm_pin" -d .venv/wheelhouse 2>&1 \
     | { grep -v "^WARNING: Location .* is ignored" || true; }
site_packages="$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
[ "$(cat "$site_packages/ftc-checkout.pth" 2>/dev/null)" = "$root/python" ] \
  || echo "$root/python" > "$site_packages/ftc-checkout.pth"

# SUNDIALS, optimised. Debian's libsundials 6.4.1 is built without optimisation
# (-O0): a CVODE step with the valves changing costs ~3x what the same source
# costs at -O2/-O3 (scripts/bench.py: cvode_step_changing_us; docs/benchmarks.md).
# So CVODE (and its serial vector and fixed-point solver) is built from Debian's
# own source of that package, checked against the checksum in its .dsc, into
# build/sundials. Without network the Debian library is used (slower, same
# results to the tolerances).
sundials_version="6.4.1+dfsg1"
sundials_sha256="c61157f1d4be06c704bea40cb131eb63ba2dada161989071604d0a0959cdf04a"
sundials_prefix="$root/build/sundials"
sundials_dir="$sundials_prefix/lib/cmake/sundials"
# A build made once on this machine is kept in the user's cache, keyed by the
# source's checksum and the compiler, and copied into a fresh checkout's build/
# (the copy, not a link: the checkout's build never depends on the cache).
sundials_cache="${XDG_CACHE_HOME:-$HOME/.cache}/ftc/sundials-${sundials_sha256:0:16}-$(g++ -dumpfullversion 2>/dev/null || echo cc)"
if [ ! -f "$sundials_dir/SUNDIALSConfig.cmake" ] && [ -f "$sundials_cache/lib/cmake/sundials/SUNDIALSConfig.cmake" ]; then
  echo "setup: CVODE (Release) from $sundials_cache"
  mkdir -p build && rm -rf "$sundials_prefix" && cp -a "$sundials_cache" "$sundials_prefix"
  # its CMake files name the prefix it was installed to: point them at the copy
  { grep -rlI --null "$sundials_cache" "$sundials_prefix" || true; } \
    | xargs -0 -r sed -i "s#$sundials_cache#$sundials_prefix#g"
fi
if [ ! -f "$sundials_dir/SUNDIALSConfig.cmake" ]; then
  mkdir -p build/sundials-src
  tarball="build/sundials-src/sundials_${sundials_version}.orig.tar.xz"
  if [ ! -f "$tarball" ]; then
    echo "setup: fetching SUNDIALS ${sundials_version} source from Debian's archive"
    curl -fsSL --retry 2 -o "$tarball.part" \
      "http://deb.debian.org/debian/pool/main/s/sundials/sundials_${sundials_version}.orig.tar.xz" \
      && mv "$tarball.part" "$tarball" || rm -f "$tarball.part"
  fi
  if [ -f "$tarball" ] && echo "$sundials_sha256  $tarball" | sha256sum -c --quiet - 2>/dev/null; then
    echo "setup: building CVODE (Release) into build/sundials"
    rm -rf build/sundials-src/src build/sundials-src/build
    mkdir -p build/sundials-src/src
    tar -xJf "$tarball" -C build/sundials-src/src --strip-components=1
    if cmake -S build/sundials-src/src -B build/sundials-src/build -DCMAKE_BUILD_TYPE=Release \
         -DCMAKE_INSTALL_PREFIX="$sundials_prefix" -DBUILD_CVODE=ON -DBUILD_ARKODE=OFF \
         -DBUILD_CVODES=OFF -DBUILD_IDA=OFF -DBUILD_IDAS=OFF -DBUILD_KINSOL=OFF \
         -DBUILD_SHARED_LIBS=ON -DBUILD_STATIC_LIBS=OFF -DEXAMPLES_ENABLE_C=OFF \
         -DEXAMPLES_INSTALL=OFF > build/sundials-src/build.log 2>&1 \
       && cmake --build build/sundials-src/build -j"$(nproc)" >> build/sundials-src/build.log 2>&1 \
       && cmake --install build/sundials-src/build >> build/sundials-src/build.log 2>&1; then
      rm -rf build/sundials-src/src build/sundials-src/build
      mkdir -p "$(dirname "$sundials_cache")" && rm -rf "$sundials_cache.part" \
        && cp -a "$sundials_prefix" "$sundials_cache.part" \
        && { grep -rlI --null "$sundials_prefix" "$sundials_cache.part" || true; } \
             | xargs -0 -r sed -i "s#$sundials_prefix#$sundials_cache#g" \
        && rm -rf "$sundials_cache" && mv "$sundials_cache.part" "$sundials_cache" || true
    else
      echo "setup: note: building SUNDIALS failed (build/sundials-src/build.log); using Debian's" >&2
      rm -rf "$sundials_prefix"
    fi
  else
    rm -f "$tarball"
    echo "setup: note: SUNDIALS source unavailable or checksum mismatch; using Debian's library" >&2
  fi
fi
sundials_flag=()
[ -f "$sundials_dir/SUNDIALSConfig.cmake" ] && sundials_flag=(-DSUNDIALS_DIR="$sundials_dir")

lcm_cmake="$(.venv/bin/python -c 'import lcm, os; print(os.path.join(os.path.dirname(os.path.dirname(lcm.__file__)), "lib", "lcm", "cmake"))')"
pybind_cmake="$(.venv/bin/python -m pybind11 --cmakedir)"
# (re)configure when there is no build yet or it was configured with another SUNDIALS
want_sundials="${sundials_flag[0]:-}"; want_sundials="${want_sundials#-DSUNDIALS_DIR=}"
have_sundials="$(sed -n 's/^SUNDIALS_DIR:[A-Z]*=//p' build/CMakeCache.txt 2>/dev/null || true)"
if [ ! -f build/Makefile ] || { [ -n "$want_sundials" ] && [ "$have_sundials" != "$want_sundials" ]; }; then
  cmake -S . -B build -DCMAKE_BUILD_TYPE=Release "${sundials_flag[@]}" \
    -Dlcm_DIR="$lcm_cmake" -Dpybind11_DIR="$pybind_cmake" \
    -DPython_EXECUTABLE="$root/.venv/bin/python" >/dev/null
fi
if ! cmake --build build -j"$(nproc)" > build/build.log 2>&1; then
  cat build/build.log >&2
  echo "setup: build failed (full log: build/build.log)" >&2
  exit 1
fi
if [ -n "${compile_pid:-}" ]; then
  wait "$compile_pid" || true
  echo "$stamp_after_compile" > "$stamp"
fi
echo "setup: ready (build/plant, .venv)"
