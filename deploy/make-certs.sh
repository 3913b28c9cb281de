#!/usr/bin/env bash
# Make a private CA and the TLS certificates of a mam deployment (see docs/DEPLOY.md).
#
#   deploy/make-certs.sh DIR [ROUTER_NAME_OR_IP ...]
#
# Writes into DIR:
#   ca.pem, ca.key                   the CA (keep ca.key off the cluster; only ca.pem is shipped)
#   router.pem, router.key           the router's server certificate, CN=router; its subjectAltName
#                                    holds localhost, 127.0.0.1 and every ROUTER_NAME_OR_IP given
#                                    (clients verify the name they connect to against it)
#   learner.pem/.key, referee.pem/.key, worker.pem/.key, monitor.pem/.key
#                                    client certificates, CN = the role name: the router's access
#                                    control matches clients by this common name
#
# An existing CA in DIR is reused (so certificates made later still chain to it); existing
# certificates are replaced. ROLES="learner worker" limits or extends the client roles.
# Certificates are valid DAYS days (default 825). Needs openssl >= 1.1.1.
set -euo pipefail

usage() { awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' "$0"; exit "${1:-0}"; }
[[ $# -ge 1 ]] || usage 2
[[ $1 == -h || $1 == --help ]] && usage 0

dir=$1; shift
days=${DAYS:-825}
roles=${ROLES:-"learner referee worker monitor"}
for role in $roles; do
    [[ $role =~ ^[A-Za-z0-9_.-]+$ ]] || { echo "bad role name: $role" >&2; exit 2; }
done
mkdir -p "$dir"
umask 077

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

newkey() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

# -- the CA ---------------------------------------------------------------------------------------
if [[ ! -s $dir/ca.key || ! -s $dir/ca.pem ]]; then
    newkey "$dir/ca.key"
    openssl req -x509 -new -key "$dir/ca.key" -sha256 -days "$((days + 365))" -subj "/CN=mam-ca-$(openssl rand -hex 4)" \
        -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" \
        -addext "subjectKeyIdentifier=hash" \
        -out "$dir/ca.pem"
    echo "made CA       $dir/ca.pem"
else
    echo "reusing CA    $dir/ca.pem"
fi

# issue NAME CN EXT_FILE: NAME.key + NAME.pem signed by the CA
issue() {
    local name=$1 cn=$2 ext=$3
    newkey "$dir/$name.key"
    openssl req -new -key "$dir/$name.key" -subj "/CN=$cn" -out "$tmp/$name.csr"
    openssl x509 -req -in "$tmp/$name.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" -CAcreateserial \
        -CAserial "$tmp/ca.srl" -sha256 -days "$days" -extfile "$ext" -out "$dir/$name.pem" 2>/dev/null
    echo "made $(printf '%-8s' "$name") $dir/$name.pem  (CN=$cn)"
}

# -- the router: a server certificate for every name clients may dial -----------------------------
san="DNS:localhost,IP:127.0.0.1"
for host in "$@"; do
    if [[ $host =~ ^[0-9.]+$ || $host == *:* ]]; then san+=",IP:$host"; else san+=",DNS:$host"; fi
done
cat >"$tmp/router.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san
EOF
issue router router "$tmp/router.ext"

# -- one client certificate per role, CN = role -----------------------------------------------------
for role in $roles; do
    cat >"$tmp/$role.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=clientAuth
subjectAltName=DNS:$role
EOF
    issue "$role" "$role" "$tmp/$role.ext"
done

chmod 600 "$dir"/*.key
chmod 644 "$dir"/*.pem
echo "done: ship ca.pem plus ROLE.pem/ROLE.key to each host (router.* to the router host)"
