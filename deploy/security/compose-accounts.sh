#!/usr/bin/env bash
# The accounts and identity keys of docker-compose.yml: run once before `docker compose up`.
#
#   deploy/security/compose-accounts.sh [ENV_FILE]        # default: .env beside the compose file
#
# 1. ENV_FILE is created from deploy/env.example if missing; each *_PASSWORD variable
#    below that is empty there gets a random 24-character password (existing ones are
#    kept, so running the script again changes nothing).
# 2. deploy/security/passwd (or $PASSWD_FILE) is created or extended with
#    deploy/security/make-passwd.sh (`ldm passwd`, passwords on its stdin): one salted
#    hash per account. Other accounts already in it (your participants, added with
#    make-passwd.sh) are kept.
# 3. deploy/security/health/mosquitto_sub (or in $HEALTH_DIR): the brokers' health check
#    options, user laas-health and its password (not on the check's command line).
# 4. deploy/security/keys/ (or $KEYS_DIR) gets each service's Ed25519 identity key
#    (`ldm keys new`) unless the file exists: an existing key is never overwritten. The
#    PUBLIC keys go into ENV_FILE (as `ldm keys show` prints them from the key files),
#    where compose finds them for the cores' --trust-service and the simulator's pins.
#
# Accounts (variable -> account names):
#   LDM_CORE_USER_PASSWORD     ldm-core-user      user-cluster core, on broker-user and the backbone
#   LDM_CORE_SERVICE_PASSWORD  ldm-core-service   service-cluster core, on broker-service and the backbone
#   LAAS_WORKER_PASSWORD       laas-worker        the LaaS worker, on broker-service
#   LAAS_HEALTH_PASSWORD       laas-health        the brokers' health checks ($SYS/broker/version)
#   LAAS_SIM_PASSWORD          sim-car sim-cyclist-1 sim-cyclist-2   the simulator's road users
#   LAAS_OWNTRACKS_PASSWORD    laas-owntracks     the OwnTracks bridge (profile bridges)
#   LAAS_CAM_PASSWORD          laas-cam           the CAM bridge (profile bridges)
#   LAAS_DEVICE_PASSWORD       (none yet)         the bridges' devices: add ot.USER.DEVICE and
#                                                 cam.UUID.STATION with make-passwd.sh
#
# Identity keys (key file in deploy/security/keys/ -> public key variable):
#   laas-worker.key    LAAS_SERVICE_KEY   the worker signs the laas service with it; both
#                                         cores and the simulator take only that signature
#   core-user.key      LAAS_CORE_KEY      the user-cluster core signs its notices and
#                                         service lists; participants (the simulator) pin it
#   core-service.key   (none)             the service-cluster core's signatures
#
# The brokers run as uid 1883 in their containers and read the password file through a
# read-only mount: as root the script gives it to 1883 with mode 0640; otherwise it
# makes it 0644 (hashes only, of random passwords) unless MODE is set (make-passwd.sh).
# The Python services run as the image's user, uid 10001 (Dockerfile; KEY_UID), and each
# reads its own key through a read-only mount: as root the script gives each new key to
# that uid with mode 0400; otherwise a new key is 0644 (unless KEY_MODE is set) in a
# keys directory of mode 0700, which keeps other users of the host out. Needs the ldm
# command (on PATH, else the repository's .venv/bin/ldm, else python3 -m ldm), not
# Mosquitto.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
env_file=${1:-$root/.env}
passwd=${PASSWD_FILE:-$here/passwd}

[ -e "$env_file" ] || { cp "$root/deploy/env.example" "$env_file"; chmod 0600 "$env_file"; }

value() { # the last VAR=value of the env file, empty if none
  sed -n "s/^$1=//p" "$env_file" | tail -n 1
}

set_value() { # VAR=value in place of the variable's first line (later ones dropped), or appended
  local tmp
  tmp=$(mktemp "$env_file.XXXXXX")
  NAME=$1 VALUE=$2 awk '
    index($0, ENVIRON["NAME"] "=") == 1 {
      if (!done) print ENVIRON["NAME"] "=" ENVIRON["VALUE"]
      done = 1
      next
    }
    { print }
    END { if (!done) print ENVIRON["NAME"] "=" ENVIRON["VALUE"] }
  ' "$env_file" >"$tmp"
  chmod 0600 "$tmp"
  mv "$tmp" "$env_file"
}

entries=()
for pair in \
  LDM_CORE_USER_PASSWORD=ldm-core-user \
  LDM_CORE_SERVICE_PASSWORD=ldm-core-service \
  LAAS_WORKER_PASSWORD=laas-worker \
  LAAS_HEALTH_PASSWORD=laas-health \
  LAAS_SIM_PASSWORD=sim-car,sim-cyclist-1,sim-cyclist-2 \
  LAAS_OWNTRACKS_PASSWORD=laas-owntracks \
  LAAS_CAM_PASSWORD=laas-cam \
  LAAS_DEVICE_PASSWORD=; do # the devices' accounts: added as devices join (docs/bridges.md)
  var=${pair%%=*}
  password=$(value "$var")
  if [ -z "$password" ]; then
    password=$(head -c 24 /dev/urandom | base64 | tr -d '+/=' | cut -c 1-24)
    set_value "$var" "$password"
    echo "$var: new password in $env_file"
  fi
  IFS=, read -r -a users <<<"${pair#*=}"
  for user in "${users[@]}"; do
    entries+=("$user=$password")
  done
done

# The env file holds these accounts' passwords: the file gets them (REPLACE=1); the
# other accounts in it are kept. make-passwd.sh makes it readable by the brokers.
printf '%s\n' "${entries[@]}" | REPLACE=1 "$here/make-passwd.sh" "$passwd" -
echo "accounts of docker-compose.yml in $passwd"

# The brokers' health check logs in as laas-health with the options in this file (read
# by mosquitto_sub from $XDG_CONFIG_HOME), so the password is on no command line that
# `docker inspect` shows. Rewritten each run, from the env file's password; readable by
# the brokers (uid 1883) as the password file is.
health=${HEALTH_DIR:-$here/health}
[ -d "$health" ] || mkdir -m 0755 "$health"
tmp=$(mktemp "$health/.mosquitto_sub.XXXXXX")
printf -- '-u laas-health\n-P %s\n' "$(value LAAS_HEALTH_PASSWORD)" >"$tmp"
if [ "$(id -u)" = 0 ] && [ -z "${MODE:-}" ]; then
  chmod 0640 "$tmp"
  chown 1883:1883 "$tmp"
else
  chmod "${MODE:-0644}" "$tmp"
fi
mv "$tmp" "$health/mosquitto_sub"
echo "the brokers' health check options in $health/mosquitto_sub"

# The identity keys: made once, never overwritten; ENV_FILE holds their public keys.
if command -v ldm >/dev/null; then
  ldm=(ldm)
elif [ -x "$root/.venv/bin/ldm" ]; then
  ldm=("$root/.venv/bin/ldm")
elif python3 -c 'import ldm.security.identity' 2>/dev/null; then
  ldm=(python3 -m ldm)
else
  echo "$0: the ldm command is not installed; run 'pip install -e .' in $root" >&2
  exit 1
fi
keys=${KEYS_DIR:-$here/keys}
[ -d "$keys" ] || mkdir -m 0700 "$keys" # its parent exists: deploy/security
for pair in laas-worker=LAAS_SERVICE_KEY core-user=LAAS_CORE_KEY core-service=; do
  file=$keys/${pair%%=*}.key
  var=${pair#*=}
  if [ -e "$file" ] || [ -L "$file" ]; then
    public=$("${ldm[@]}" keys show "$file") # fails on anything but a readable key
  else
    public=$("${ldm[@]}" keys new "$file") # mode 0600, the invoking user's
    if [ "$(id -u)" = 0 ] && [ -z "${KEY_MODE:-}" ]; then
      chown "${KEY_UID:-10001}" "$file"
      chmod 0400 "$file"
    else
      chmod "${KEY_MODE:-0644}" "$file"
    fi
    echo "$file: new identity key"
  fi
  if [ -n "$var" ] && [ "$(value "$var")" != "$public" ]; then
    set_value "$var" "$public"
    echo "$var: public key of $file in $env_file"
  fi
done
echo "identity keys of docker-compose.yml in $keys; now: docker compose up -d"
