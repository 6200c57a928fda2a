#!/bin/sh
# Make a fleet CA and one certificate per identity, with the openssl CLI (no Python packages).
#   comms/zenoh_configs/make_certs.sh OUTDIR router gcs-1 vehicle-1 vehicle-2 ...
# Writes OUTDIR/ca.pem, OUTDIR/ca.key and OUTDIR/<name>.pem + <name>.key (mode 0600) per name.
# The common name is the identity the router's access control matches (cert_common_names).
# Certificates name localhost and 127.0.0.1; set COVEY_CERT_SAN (e.g. "DNS:gcs.local,IP:10.0.0.1")
# for real hosts. Validity: COVEY_CERT_DAYS (default 30). An existing CA in OUTDIR is reused.
set -eu
out=$1; shift
days=${COVEY_CERT_DAYS:-30}
san=${COVEY_CERT_SAN:-DNS:localhost,IP:127.0.0.1}
umask 077
mkdir -p "$out"
if [ ! -f "$out/ca.pem" ]; then
  openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days "$days" \
    -subj "/CN=covey-fleet-ca" -keyout "$out/ca.key" -out "$out/ca.pem" 2>/dev/null
fi
ext="$out/.ext.cnf"
printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n' "$san" >"$ext"
for name in "$@"; do
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -subj "/CN=$name" \
    -keyout "$out/$name.key" -out "$out/$name.csr" 2>/dev/null
  openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca.key" -CAcreateserial \
    -days "$days" -extfile "$ext" -out "$out/$name.pem" 2>/dev/null
  rm -f "$out/$name.csr"
done
rm -f "$ext"
chmod 644 "$out"/*.pem
