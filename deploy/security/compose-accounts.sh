#!/usr/bin/env bash
# The accounts of docker-compose.yml: run once before `docker compose up`.
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
#
# Accounts (variable -> account names):
#   LDM_CORE_USER_PASSWORD     ldm-core-user      user-cluster core, on broker-user and the backbone
#   LDM_CORE_SERVICE_PASSWORD  ldm-core-service   service-cluster core, on broker-service and the backbone
#   LAAS_WORKER_PASSWORD       laas-worker        the LaaS worker, on broker-service
#   LAAS_HEALTH_PASSWORD       laas-health        the brokers' health checks ($SYS/broker/version)
#   LAAS_SIM_PASSWORD          sim-car sim-cyclist-1 sim-cyclist-2   the simulator's road users
#
# The brokers run as uid 1883 in their containers and read the file through a read-only
# mount: as root the script gives it to 1883 with mode 0640; otherwise it makes it 0644
# (hashes only, of random passwords) unless MODE is set. Needs the ldm command (see
# make-passwd.sh), not Mosquitto.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
env_file=${1:-$root/.env}
passwd=${PASSWD_FILE:-$here/passwd}

[ -e "$env_file" ] || { cp "$root/deploy/env.example" "$env_file"; chmod 0600 "$env_file"; }

value() { # the last VAR=value of the env file, empty if none
  sed -n "s/^$1=//p" "$env_file" | tail -n 1
}

set_value() { # VAR=value, replacing the variable's lines or appending one
  local tmp
  tmp=$(mktemp "$env_file.XXXXXX")
  grep -v "^$1=" "$env_file" >"$tmp" || true
  printf '%s=%s\n' "$1" "$2" >>"$tmp"
  chmod 0600 "$tmp"
  mv "$tmp" "$env_file"
}

entries=()
for pair in \
  LDM_CORE_USER_PASSWORD=ldm-core-user \
  LDM_CORE_SERVICE_PASSWORD=ldm-core-service \
  LAAS_WORKER_PASSWORD=laas-worker \
  LAAS_HEALTH_PASSWORD=laas-health \
  LAAS_SIM_PASSWORD=sim-car,sim-cyclist-1,sim-cyclist-2; do
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

if [ "$(id -u)" = 0 ] && [ -z "${MODE:-}" ]; then
  printf '%s\n' "${entries[@]}" | MODE=0640 "$here/make-passwd.sh" "$passwd" -
  chown 1883:1883 "$passwd"
else
  printf '%s\n' "${entries[@]}" | MODE=${MODE:-0644} "$here/make-passwd.sh" "$passwd" -
fi
echo "accounts of docker-compose.yml in $passwd; now: docker compose up -d"
