#!/usr/bin/env bash
# A certificate authority and a server certificate for the user-cluster broker's TLS
# listener (docker-compose.tls.yml), made with openssl.
#
#   deploy/security/make-tls-cert.sh HOST [DIR]     # DIR: default deploy/security/tls
#
# HOST is the name (or IP address) participants connect to: the certificate is valid for
# it alone (subjectAltName). DIR (mode 0700, never committed) gets:
#   ca.crt      the CA certificate: give it to every participant (OwnTracks: install it
#               on the phone; ldm/laas clients: --ca-file ca.crt), it is public
#   ca.key      the CA's private key: keep it offline; it signs certificates
#   server.crt  the broker's certificate (signed by the CA, 825 days)
#   server.key  the broker's private key: run as root, the script gives it to uid 1883,
#               the user eclipse-mosquitto reads it as, mode 0400; run as another user,
#               it makes it mode 0644 in the 0700 folder (compose mounts the file
#               itself, so only the container and you can read it)
# Existing files are never overwritten: remove DIR's server.* to make a new server
# certificate with the same CA. Keys are ECDSA P-256.
set -euo pipefail
if [ "$#" -lt 1 ] || [ "$#" -gt 2 ]; then
  echo "usage: $0 HOST [DIR]" >&2
  exit 2
fi
here=$(cd "$(dirname "$0")" && pwd)
host=$1
dir=${2:-$here/tls}
command -v openssl >/dev/null || {
  echo "$0: openssl is not installed (apt-get install openssl)" >&2
  exit 1
}
if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then
  san="IP:$host"
else
  san="DNS:$host"
fi
[ -d "$dir" ] || mkdir -m 0700 "$dir"
cd "$dir"
if [ -e server.crt ] || [ -e server.key ]; then
  echo "$0: $dir/server.crt or server.key exists; not overwriting (remove them first)" >&2
  exit 2
fi
curve=(-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes)
if [ ! -e ca.crt ]; then
  (umask 077 && openssl req -x509 "${curve[@]}" -days 3650 -subj "/CN=LaaS broker CA" \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
    -keyout ca.key -out ca.crt 2>/dev/null)
  chmod 0644 ca.crt
  echo "$0: new CA in $dir/ca.crt (its key: ca.key, keep it offline)" >&2
fi
(umask 077 && openssl req "${curve[@]}" -subj "/CN=$host" -keyout server.key -out server.csr \
  2>/dev/null)
printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth\nbasicConstraints=CA:FALSE\n' "$san" \
  >server.ext
openssl x509 -req -in server.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days 825 \
  -extfile server.ext -out server.crt 2>/dev/null
rm -f server.csr server.ext
chmod 0644 server.crt
if [ "$(id -u)" = 0 ]; then
  chown 1883:1883 server.key
  chmod 0400 server.key
  echo "$0: $dir/server.key is mode 0400, owned by 1883 (eclipse-mosquitto)" >&2
else
  chmod 0644 server.key
  echo "$0: $dir/server.key is mode 0644 in a folder of mode 0700" >&2
fi
echo "$0: server certificate for $san in $dir/server.crt; participants need $dir/ca.crt" >&2
