#!/usr/bin/env bash
# Install everything the test suite needs on a fresh Debian machine, then run it.
#   - Debian packages: PostgreSQL (the store tests run against a real server)
#     Python's venv module, and Chromium (the web editor's end-to-end tests).
#   - a virtual environment in .venv with lanemap and its test extras.
# Extra arguments are passed to pytest, e.g. `bash scripts/test.sh -k store`.
set -euo pipefail
cd "$(dirname "$0")/.."

as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }
as_postgres() {
  if [ "$(id -u)" -eq 0 ]; then runuser -u postgres -- "$@"; else sudo -u postgres "$@"; fi
}

missing=()
command -v pg_ctlcluster >/dev/null 2>&1 || missing+=(postgresql)
python3 -c 'import ensurepip, venv' >/dev/null 2>&1 || missing+=(python3-venv)
[ -x /usr/bin/chromium ] || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
  echo "== installing Debian packages: ${missing[*]}"
  as_root apt-get update -qq
  DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

if ! pg_isready -h 127.0.0.1 -p 5432 -q; then
  echo "== starting PostgreSQL"
  version=$(ls /etc/postgresql | sort -V | tail -n 1)
  as_root pg_ctlcluster --skip-systemctl-redirect "$version" main start || true
  for _ in $(seq 1 30); do pg_isready -h 127.0.0.1 -p 5432 -q && break; sleep 1; done
fi
if ! pg_isready -h 127.0.0.1 -p 5432 -q; then
  echo "error: PostgreSQL could not be started on 127.0.0.1:5432" >&2
  exit 1
fi
# The tests log in over TCP as postgres/postgres (Debian's default is scram on 127.0.0.1).
as_postgres psql -qc "ALTER USER postgres PASSWORD 'postgres'" >/dev/null
export LANEMAP_TEST_POSTGRES_URL="${LANEMAP_TEST_POSTGRES_URL:-postgresql://postgres:postgres@127.0.0.1:5432/postgres}"

if [ ! -x .venv/bin/python ]; then
  echo "== creating .venv"
  python3 -m venv .venv
fi
echo "== installing lanemap and its test dependencies"
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'

# The fault tests simulate a full disk (and, as root, a read-only folder) with
# tmpfs mounts, as root or through sudo: the rights this script installs
# packages with. Without mount they fail; they never skip.

echo "== running the test suite"
exec .venv/bin/python -m pytest -n 2 --dist loadfile "$@"
