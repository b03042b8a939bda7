#!/usr/bin/env bash
# Create or extend a Mosquitto password file with `ldm passwd` (no Mosquitto needed).
#
#   deploy/security/make-passwd.sh FILE USER[=PASSWORD] ...
#
# A USER without =PASSWORD gets a random 24-character password, printed once as
# USER=PASSWORD on stdout (hand it to that account's owner; it is not kept anywhere
# else). The entry - reads USER[=PASSWORD] lines from stdin, which keeps passwords out
# of the process list. FILE is created if missing and stores only salted hashes
# (Mosquitto 2's PBKDF2-SHA512 format); other accounts in it are kept. Keep it out of
# git and readable by the broker only (the script sets mode 0640 unless MODE is set).
#
# The ldm command is the one on PATH, else the repository's .venv/bin/ldm (after
# `pip install -e .`), else `python3 -m ldm` where python3 can import ldm.
set -euo pipefail
if [ "$#" -lt 2 ]; then
  echo "usage: $0 FILE USER[=PASSWORD] ..." >&2
  exit 2
fi
root=$(cd "$(dirname "$0")/../.." && pwd)
if command -v ldm >/dev/null; then
  ldm=(ldm)
elif [ -x "$root/.venv/bin/ldm" ]; then
  ldm=("$root/.venv/bin/ldm")
elif python3 -c 'import ldm.ops.passwd' 2>/dev/null; then
  ldm=(python3 -m ldm)
else
  echo "$0: the ldm command is not installed; run 'pip install -e .' in $root" \
    "(or bash scripts/test, which sets up .venv)" >&2
  exit 1
fi
file=$1
shift
exec "${ldm[@]}" passwd --mode "${MODE:-0640}" -- "$file" "$@"
