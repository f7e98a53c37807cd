# What scripts/container and scripts/proxy-image share: the container engine, the labels'
# values, and a root filesystem staged from the machine's own binaries. Sourced, not run.

# $engine: podman or docker, whichever is installed ($CONTAINER_ENGINE picks one).
pick_engine() {
  engine="${CONTAINER_ENGINE:-}"
  if [ -z "$engine" ]; then
    if command -v podman >/dev/null; then
      engine=podman
    elif command -v docker >/dev/null; then
      engine=docker
    else
      echo "error: neither podman nor docker is installed (apt-get install podman, or docker.io)" >&2
      exit 1
    fi
  fi
}

# $version, $repository, $revision, $created: prac's version and repository (Cargo.toml), the
# git commit, and now (or SOURCE_DATE_EPOCH, which makes the label reproducible).
read_labels() {
  version="$(sed -n 's/^version = "\(.*\)"$/\1/p' Cargo.toml | head -n 1)"
  [ -n "$version" ] || { echo "error: no version in Cargo.toml" >&2; exit 1; }
  repository="$(sed -n 's/^repository = "\(.*\)"$/\1/p' Cargo.toml | head -n 1)"
  revision="$(git rev-parse HEAD 2>/dev/null || echo unknown)"
  created="$(date -u -d "@${SOURCE_DATE_EPOCH:-$(date +%s)}" +%Y-%m-%dT%H:%M:%SZ)"
}

# Writes the record (/var/lib/dpkg/status.d/, where image scanners read them) and copyright of
# the Debian package that owns file $2 into rootfs $1, once per package. dpkg knows a file by
# the path its package installed it at, which with a merged /usr may be the path ldd gives, its
# target, or that without /usr.
record_package() {
  local rootfs="$1" package="" path
  command -v dpkg-query >/dev/null || return 0
  for path in "$2" "$(readlink -f "$2")" "$(readlink -f "$2" | sed 's#^/usr/#/#')"; do
    package="$(dpkg-query -S "$path" 2>/dev/null | head -n 1 | cut -d: -f1)" || true
    [ -z "$package" ] || break
  done
  if [ -n "$package" ] && [ ! -e "$rootfs/var/lib/dpkg/status.d/$package" ]; then
    mkdir -p "$rootfs/var/lib/dpkg/status.d"
    dpkg-query -s "$package" >"$rootfs/var/lib/dpkg/status.d/$package"
    if [ -f "/usr/share/doc/$package/copyright" ]; then
      mkdir -p "$rootfs/usr/share/doc/$package"
      cp "/usr/share/doc/$package/copyright" "$rootfs/usr/share/doc/$package/"
    fi
  fi
}

# Copies the C libraries binary $2 links against into rootfs $1, at the paths the dynamic loader
# looks in, with their packages' records.
stage_libraries() {
  local rootfs="$1" lib
  for lib in $(ldd "$2" | grep -o '/[^ ]*'); do
    mkdir -p "$rootfs$(dirname "$lib")"
    cp -L "$lib" "$rootfs$lib"
    record_package "$rootfs" "$lib"
  done
}

# /etc/passwd and /etc/group with root and nonroot (65532, distroless's), into rootfs $1.
stage_users() {
  mkdir -p "$1/etc"
  printf 'root:x:0:0:root:/root:/sbin/nologin\nnonroot:x:65532:65532:nonroot:/home/nonroot:/sbin/nologin\n' \
    >"$1/etc/passwd"
  printf 'root:x:0:\nnonroot:x:65532:\n' >"$1/etc/group"
}

# Prints "TAG: SIZE MB (BYTES bytes)" for image $1.
print_size() {
  local size
  size="$("$engine" image inspect --format '{{.Size}}' "$1")"
  echo "$1: $(awk -v b="$size" 'BEGIN { printf "%.1f MB (%d bytes)", b / 1e6, b }')"
}
