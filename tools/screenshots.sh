#!/usr/bin/env bash
# Renew the README's screenshots in docs/screenshots/:
# - viewer.png: the viewer on the embedded default world, in headless
#   Chromium (Debian's `chromium`), as a visitor without the token sees it;
# - WORLD.png: the last frame of each shipped world after a short run.
# Usage: bash tools/screenshots.sh   (takes a few minutes)
set -euo pipefail
cd "$(dirname "$0")/.."
out=docs/screenshots
mkdir -p "$out"
cargo build --release -q
bw=target/release/brickworld
chromium=${BRICKWORLD_CHROMIUM:-/usr/bin/chromium}
[ -x "$chromium" ] || { echo "error: $chromium not found (apt-get install chromium)" >&2; exit 1; }
tmp=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$tmp"' EXIT

# The viewer: the default world running, the page given 8 s to fill its charts.
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
"$bw" run --state "$tmp/default" --addr "127.0.0.1:$port" >/dev/null 2>&1 &
# Wait (up to 3 minutes) for the world to be built and a few frames drawn.
for _ in $(seq 900); do
  frames=$(curl -sf "http://127.0.0.1:$port/status" | python3 -c 'import json,sys; print(json.load(sys.stdin)["frames"])' 2>/dev/null || echo 0)
  [ "$frames" -ge 5 ] && break
  sleep 0.2
done
"$chromium" --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
  --disable-background-networking --disable-component-update --disable-sync --hide-scrollbars \
  --user-data-dir="$tmp/chromium" --window-size=1400,1000 --timeout=8000 \
  --screenshot="$out/viewer.png" "http://127.0.0.1:$port/" >/dev/null 2>&1
kill %1; wait %1 2>/dev/null || true
echo "wrote $out/viewer.png"

# A frame of each shipped world (the small ones; the continent and the
# endless world stream for minutes before they look like anything).
for w in default valley snowy_mountain sandbox caves; do
  "$bw" run "worlds/$w.toml" --state "$tmp/$w" --addr 127.0.0.1:0 --ticks 120 >/dev/null 2>&1
  cp "$(ls "$tmp/$w"/frames/frame-*.png | tail -1)" "$out/$w.png"
  echo "wrote $out/$w.png"
done
