#!/usr/bin/env bash
# Install Locus with its test tools into .venv and run the test suite.
# The suite runs on the embedded SQLite; when a PostgreSQL server answers on
# localhost (or LOCUS_TEST_POSTGRES_URL names one), the API and pipeline tests
# run a second time against it.
set -euo pipefail
cd "$(dirname "$0")/.."
python3 -m venv .venv
.venv/bin/pip install --quiet --upgrade pip
.venv/bin/pip install --quiet -e '.[dev]'
.venv/bin/ruff check app tests bench migrations
.venv/bin/ruff format --check app tests bench migrations
.venv/bin/mypy
# The dashboard's browser test drives Debian's Chromium (Playwright downloads no browser).
if ! command -v chromium >/dev/null; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
    || echo "== could not install chromium: the dashboard's browser test will be skipped"
fi
# each pass spreads its test files over two processes (pytest-xdist), which
# nearly halves the time on two cores
two_processes=(-n 2 --dist loadfile)
.venv/bin/python -m pytest "${two_processes[@]}" "$@"
pg_url="${LOCUS_TEST_POSTGRES_URL:-postgresql+psycopg://postgres@127.0.0.1:5432/postgres}"
if .venv/bin/python -c "import sqlalchemy as s, sys; s.create_engine(sys.argv[1]).connect().close()" "$pg_url" 2>/dev/null; then
  echo "== again on PostgreSQL"
  # the storage-fault and Redis-topology tests run on PostgreSQL in the first pass already
  LOCUS_TEST_POSTGRES_URL="$pg_url" .venv/bin/python -m pytest "${two_processes[@]}" tests/api tests/e2e \
    --ignore=tests/e2e/test_storage_faults.py --ignore=tests/e2e/test_redis_topology.py "$@"
else
  echo "== PostgreSQL not reachable at $pg_url: skipped the PostgreSQL run"
fi
