#!/usr/bin/env bash
# Create or extend a Mosquitto password file with mosquitto_passwd (installed with mosquitto).
#
#   deploy/security/make-passwd.sh FILE USER[=PASSWORD] ...
#
# A USER without =PASSWORD gets a random 24-character password, printed once as
# USER=PASSWORD on stdout (hand it to that account's owner; it is not kept anywhere
# else). FILE is created if missing and stores only salted hashes; keep it out of git
# and readable by the broker only (the script sets mode 0640 unless MODE is set).
set -euo pipefail
if [ "$#" -lt 2 ]; then
  echo "usage: $0 FILE USER[=PASSWORD] ..." >&2
  exit 2
fi
file=$1
shift
passwd_bin=${MOSQUITTO_PASSWD:-$(command -v mosquitto_passwd || echo /usr/bin/mosquitto_passwd)}
if [ ! -x "$passwd_bin" ]; then
  echo "$0: mosquitto_passwd not found (apt-get install mosquitto)" >&2
  exit 1
fi
[ -e "$file" ] || : >"$file"
for entry in "$@"; do
  user=${entry%%=*}
  if [ "$entry" = "$user" ]; then
    password=$(head -c 18 /dev/urandom | base64 | tr '+/' '-_')
    echo "$user=$password"
  else
    password=${entry#*=}
  fi
  case $user in
    '' | *[!A-Za-z0-9._:-]*) echo "$0: bad user name '$user'" >&2; exit 2 ;;
  esac
  "$passwd_bin" -b "$file" "$user" "$password"
done
chmod "${MODE:-0640}" "$file"
