# Sourced by split_taichi_wheels.sh and split_ray.sh: an archive cut into pieces that each fit, beside the
# tracked tree, under the 64 MiB (counted on disk) a device `run` call carries; one staging call per piece.

# carry_room_kib: the KiB a call can carry beside the tracked tree (512 KiB kept for scripts); fails under 2 MiB
carry_room_kib() {
  local tracked room
  tracked=$(git ls-files -z | xargs -0 du -ck 2>/dev/null | tail -1 | cut -f1)
  room=$(( 64 * 1024 - tracked - 512 ))
  [ "$room" -gt 2048 ] || { echo "error: the tracked tree ($tracked KiB) leaves no room under 64 MiB" >&2; return 1; }
  echo "$room"
}

# cut_into_pieces ARCHIVE NAME ROOM_KIB: .gpu/NAME1 .. .gpu/NAMEk, each holding a piece of ARCHIVE and a
# stage.sh that copies it to /tmp/NAME-parts on the device; prints k
cut_into_pieces() {
  local archive=$1 name=$2 room=$3 dir piece n=0
  dir=$(mktemp -d)
  split -d -a 2 -b "$(( room * 1024 ))" "$archive" "$dir/part."
  for piece in "$dir"/part.*; do
    n=$((n + 1)); mkdir -p ".gpu/$name$n"; mv "$piece" ".gpu/$name$n/"
    echo "set -e; mkdir -p /tmp/$name-parts && cp .gpu/$name$n/part.* /tmp/$name-parts/ && ls /tmp/$name-parts" \
      > ".gpu/$name$n/stage.sh"
  done
  rmdir "$dir"
  echo "$n"
}

# join_pieces_lines NAME K: stage-script lines that check all K pieces arrived and unpack them (tar.xz) into
# /tmp/gpusite
join_pieces_lines() {
  local name=$1 k=$2
  cat <<S
[ \$(ls /tmp/$name-parts/part.* | wc -l) -eq $k ] || { echo "error: not all $k pieces staged (.gpu/${name}1 .. ${name}$k)" >&2; exit 1; }
mkdir -p /tmp/gpusite && cat /tmp/$name-parts/part.* | tar -C /tmp/gpusite -xJf -
S
}
