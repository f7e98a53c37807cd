#!/usr/bin/env bash
# Two `prac serve` replicas (127.0.0.1:50061, :50062) behind nginx on 127.0.0.1:50051, serving
# bundles/ (or $BUNDLES). Ctrl-C stops all three. Needs nginx (apt-get install nginx) and
# `cargo build --release`.
set -euo pipefail
cd "$(dirname "$0")/../.."
BUNDLES="${BUNDLES:-bundles}"
PREFIX="$(mktemp -d)"
trap 'kill $(jobs -p) 2>/dev/null; wait; rm -rf "$PREFIX"' EXIT INT TERM
./target/release/prac serve --listen 127.0.0.1:50061 --bundles "$BUNDLES" &
./target/release/prac serve --listen 127.0.0.1:50062 --bundles "$BUNDLES" &
sed -e "s#@PREFIX@#$PREFIX#" -e "s#@LISTEN@#127.0.0.1:50051#" \
    -e "s#@REPLICA_A@#127.0.0.1:50061#" -e "s#@REPLICA_B@#127.0.0.1:50062#" \
    deploy/nginx/prac.conf > "$PREFIX/nginx.conf"
"$(command -v nginx || echo /usr/sbin/nginx)" -p "$PREFIX" -c "$PREFIX/nginx.conf" &
wait
