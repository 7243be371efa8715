#!/usr/bin/env bash
# Generate a private certificate authority and a server certificate for the dimslam router's TLS
# endpoint (deploy/zenoh/tls-router.json5, tls-client.json5).
#
# Usage: deploy/make-certs.sh OUT_DIR [NAME ...]
#   OUT_DIR  where ca.pem, ca.key, router.pem and router.key are written (created if missing)
#   NAME     a host name or IP address clients use to reach the router, e.g. hub.lab or
#            10.0.0.1; each becomes a subjectAltName of the server certificate. localhost and
#            127.0.0.1 are always included so the router can be checked on its own machine.
#
# Clients check the router's certificate against ca.pem and against the host in their connect
# endpoint (tls/<host>:7450), so that host must be one of the NAMEs. Copy ca.pem to every
# client; router.key never leaves the router. Re-running keeps an existing CA (so clients keep
# trusting it) and issues a new server certificate. DAYS=N sets the validity (default 825).
set -euo pipefail

usage() { sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; }
if [[ $# -ge 1 && ( "$1" == "-h" || "$1" == "--help" ) ]]; then
    usage
    exit 0
fi
if [[ $# -lt 1 ]]; then
    usage >&2
    exit 2
fi
command -v openssl >/dev/null || { echo "error: openssl is not installed" >&2; exit 2; }

out=$1
shift
days=${DAYS:-825}  # certificates longer than 825 days are refused by some TLS stacks
mkdir -p "$out"
umask 077  # private keys readable by their owner only

san="DNS:localhost,IP:127.0.0.1"
for name in "$@"; do
    if [[ $name =~ ^[0-9.]+$ || $name == *:* ]]; then
        san+=",IP:$name"
    else
        san+=",DNS:$name"
    fi
done

if [[ ! -f "$out/ca.pem" ]]; then
    openssl req -x509 -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \
        -keyout "$out/ca.key" -out "$out/ca.pem" -days "$days" \
        -subj "/CN=dimslam local CA" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
    echo "created the CA: $out/ca.pem (keep $out/ca.key offline)"
fi

# rustls (zenoh's TLS) checks the subjectAltName only, never the CN, and rejects a server
# certificate without serverAuth.
openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \
    -keyout "$out/router.key" -out "$out/router.csr" -subj "/CN=dimslam router" 2>/dev/null
openssl x509 -req -in "$out/router.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" \
    -CAcreateserial -out "$out/router.pem" -days "$days" \
    -extfile <(printf '%s\n' \
        "subjectAltName=$san" \
        "basicConstraints=critical,CA:FALSE" \
        "keyUsage=critical,digitalSignature" \
        "extendedKeyUsage=serverAuth") 2>/dev/null
rm -f "$out/router.csr" "$out/ca.srl"
chmod 644 "$out/ca.pem" "$out/router.pem"
echo "created the router certificate: $out/router.pem for $san"
