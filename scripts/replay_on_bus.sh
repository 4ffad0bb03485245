#!/usr/bin/env bash
# Replays a recorded plant log onto a loopback-only LCM bus and (if Java is
# present) opens lcm-spy on it with the ftc message types decoded.
#
#   scripts/replay_on_bus.sh runs/NAME/runs/single/t00/ppo-offline/s0/plant.lcmlog [SPEED]
#
# Environment: LCM_URL (default udpm://239.255.76.67:7671?ttl=0, a port the
# plant does not use by default, so a live plant is not disturbed);
# NO_SPY=1 replays without opening lcm-spy (headless machines).
# See scripts/replay_on_bus.md for the details and for doing the steps by hand.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
log="${1:?usage: $0 LOG [SPEED]}"
speed="${2:-1.0}"
url="${LCM_URL:-udpm://239.255.76.67:7671?ttl=0}"
case "$url" in *ttl=0*) ;; *) echo "refusing $url: keep ttl=0 (loopback only)" >&2; exit 2 ;; esac
site="$("$root/.venv/bin/python" -c 'import lcm, os; print(os.path.dirname(os.path.dirname(lcm.__file__)))')"
bin="$site/bin"   # the real executables (the venv's bin/ holds Python wrappers)

if [ -z "${NO_SPY:-}" ] && command -v javac >/dev/null && command -v jar >/dev/null; then
  types="$root/build/java"
  if [ ! -f "$types/ftc_types.jar" ] || [ -n "$(find "$root/lcmtypes" -newer "$types/ftc_types.jar")" ]; then
    rm -rf "$types" && mkdir -p "$types"
    (cd "$types" && "$bin/lcm-gen" -j "$root"/lcmtypes/ftc/*.lcm \
       && javac -cp "$site/share/java/lcm.jar" ftc/*.java && jar cf ftc_types.jar ftc/*.class)
  fi
  CLASSPATH="$types/ftc_types.jar" "$bin/lcm-spy" --lcm-url="$url" &
  spy=$!
  trap 'kill "$spy" 2>/dev/null || true' EXIT
fi
"$bin/lcm-logplayer" --speed="$speed" --lcm-url="$url" "$log"
