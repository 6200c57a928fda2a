#!/bin/sh
# A fleet CA and one certificate per identity; kept for scripts: `covey tls init` (trust/tls_setup.py)
# does the same and also writes every identity's ready-to-use Zenoh config.
#   comms/zenoh_configs/make_certs.sh OUTDIR router gcs-1 vehicle-1 vehicle-2 ...
# Writes OUTDIR/ca.pem, OUTDIR/ca.key and OUTDIR/<name>.pem + <name>.key (keys mode 0600); an
# existing CA in OUTDIR is reused. Certificates name localhost, 127.0.0.1 and ::1; set
# COVEY_CERT_SAN (e.g. "DNS:gcs.local,IP:10.0.0.1") for real hosts. Validity: COVEY_CERT_DAYS
# (default 30). Runs covey's Python (the repository's .venv, else python3 with covey installed).
set -eu
root=$(CDPATH='' cd -- "$(dirname -- "$0")/../.." && pwd)
py=${COVEY_PYTHON:-$root/.venv/bin/python}
[ -x "$py" ] || py=python3
out=$1; shift
PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" exec "$py" -m covey_cli tls certs "$out" "$@" \
  --hosts "${COVEY_CERT_SAN:-localhost}" --days "${COVEY_CERT_DAYS:-30}" >/dev/null
