#!/usr/bin/env bash
# A headless screenshot of TensorBoard's dashboard for the README (docs/tensorboard.png).
#
#   bash docs/tensorboard_screenshot.sh [sweep folder] [output png]
#
# Serves the sweep (default: a fresh 4-job sweep of 300 episodes, about a minute) with tensorboard
# on 127.0.0.1 and photographs the scalars page with Debian's chromium (apt-get install chromium;
# browser downloaders such as playwright's need the internet, this does not).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${2:-docs/tensorboard.png}
sweep=${1:-}
if [ -z "$sweep" ]; then
  sweep=$(mktemp -d)/sweep
  SDL_VIDEODRIVER=dummy drone-train -m algo.lr=1e-3,1e-4 seed=0,1 hydra/launcher=fused \
    "hydra.sweep.dir=$sweep" algo.episodes=300 eval.every_episodes=100 eval.episodes=2 \
    compile=false progress=false > /dev/null
fi
port=$(python -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
python -m tensorboard.main --logdir "$sweep" --host 127.0.0.1 --port "$port" > /dev/null 2>&1 &
server=$!
trap 'kill $server' EXIT
for _ in $(seq 60); do curl -sf "http://127.0.0.1:$port/data/runs" > /dev/null && break; sleep 1; done
# The dashboard loads its charts with JavaScript: give it virtual time to draw them.
chromium --headless --no-sandbox --use-gl=angle --use-angle=swiftshader --enable-unsafe-swiftshader --hide-scrollbars --window-size=1400,1000 \
  --virtual-time-budget=20000 --screenshot="$out" \
  "http://127.0.0.1:$port/#scalars" 2> /dev/null
echo "wrote $out"
