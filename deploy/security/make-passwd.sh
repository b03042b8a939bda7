#!/usr/bin/env bash
# Create or extend a Mosquitto password file with `ldm passwd` (no Mosquitto needed).
#
#   deploy/security/make-passwd.sh FILE USER[=PASSWORD] ...
#
# A USER without =PASSWORD gets a random 24-character password, printed once as
# USER=PASSWORD on stdout (hand it to that account's owner; it is not kept anywhere
# else). The entry - reads USER[=PASSWORD] lines from stdin, which keeps passwords out
# of the process list. FILE is created if missing and stores only salted hashes
# (Mosquitto 2's PBKDF2-SHA512 format). Adding accounts never changes another one: the
# accounts already in FILE keep their passwords, including one named again here (a note
# on stderr says so), unless REPLACE=1 is set, which gives those the new passwords.
#
# Who can read FILE: the brokers of docker-compose.yml (eclipse-mosquitto) read it as
# uid 1883 through a read-only mount. Run as root, the script makes FILE mode 0640 and
# gives it to 1883:1883 (OWNER=USER:GROUP gives it to another, e.g. OWNER=mosquitto: for
# a Mosquitto installed on the host); run as another user, it makes FILE mode 0644 (it
# holds salted hashes of the passwords, never the passwords), as a non-root user cannot
# give a file away. MODE=... sets the mode instead (then no owner is changed unless
# OWNER is set). The script says on stderr which it did. Keep FILE out of git.
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
owner=${OWNER:-}
if [ -n "${MODE:-}" ]; then
  mode=$MODE
elif [ "$(id -u)" = 0 ]; then
  mode=0640
  owner=${owner:-1883:1883}
else
  mode=0644
fi
replace=()
if [ "${REPLACE:-0}" = 1 ]; then
  replace=(--replace)
fi
"${ldm[@]}" passwd --mode "$mode" "${replace[@]}" -- "$file" "$@"
if [ -n "$owner" ]; then
  chown "$owner" "$file"
  echo "$0: $file is mode $mode, owned by $owner (eclipse-mosquitto reads it as 1883)" >&2
else
  echo "$0: $file is mode $mode, owned by $(id -un 2>/dev/null || id -u); Mosquitto reads it as another" \
    "user only if the mode lets others read (0644)" >&2
fi
