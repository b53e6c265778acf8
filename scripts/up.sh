#!/usr/bin/env bash
# `make up`: the emulator service on http://$HOST:$PORT (default 127.0.0.1:8000), without Docker.
# Redis comes from scripts/redis.sh (REDIS_URL, else 127.0.0.1:6379, else a redis-server it starts and
# stops again on exit); the artifacts from $ARTIFACTS_DIR (default artifacts/). Ctrl-C stops both.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}

pidfile=$(mktemp)
child=""
cleanup() {
  if [[ -n "$child" ]] && kill -TERM "$child" 2>/dev/null; then
    wait "$child" 2>/dev/null || true
  fi
  if [[ -s "$pidfile" ]]; then
    kill "$(cat "$pidfile")" 2>/dev/null || true
    echo "up.sh: stopped the redis-server it had started" >&2
  fi
  rm -f "$pidfile"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

if url=$(scripts/redis.sh --pidfile "$pidfile"); then
  export REDIS_URL=$url
else
  echo "up.sh: no Redis: serving without persistence" >&2
  export REDIS_URL=""
fi
export ARTIFACTS_DIR=${ARTIFACTS_DIR:-artifacts} HOST=${HOST:-127.0.0.1} PORT=${PORT:-8000}
echo "up.sh: emulator on http://$HOST:$PORT (artifacts: $ARTIFACTS_DIR, Redis: ${REDIS_URL:-none})" >&2
"$PYTHON" -m services.emulator &
child=$!
wait "$child"
