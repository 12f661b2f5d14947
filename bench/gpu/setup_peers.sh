# Unpack the GPU peers of bench/bench_gpu.py (.peers/, from bench/gpu/fetch_peers.sh) on the GPU machine
# and put them on PYTHONPATH. Source it from the repository root:
#
#     . bench/gpu/setup_peers.sh            # → PYTHONPATH=/tmp/peers:$PYTHONPATH
#
# or run it (bash bench/gpu/setup_peers.sh) and eval the `export PYTHONPATH=...` line it prints last.
# PEERS_SRC (default .peers) and PEERS_DIR (default /tmp/peers) override the folders. There is no
# `unzip` on that machine: the zips are unpacked with `python3 -m zipfile -e`. Unpacking twice is
# skipped (PEERS_DIR/.unpacked lists what was unpacked). Missing .peers/ is not an error: the benchmark
# then reports the peers as not importable and still runs tofcore.

_tofpeers_setup() {
    local src=${PEERS_SRC:-.peers} dir=${PEERS_DIR:-/tmp/peers} py=${PYTHON:-python3} f list
    if ! ls "$src"/*.zip "$src"/*.whl >/dev/null 2>&1; then
        echo "setup_peers: no wheels in $src/ (run bench/gpu/fetch_peers.sh where there is internet," \
             "carry .peers); the peers will be skipped" >&2
        return 0
    fi
    list=$(cd "$src" && ls -1 *.zip *.whl 2>/dev/null)
    if [ ! -f "$dir/.unpacked" ] || [ "$(cat "$dir/.unpacked")" != "$list" ]; then
        rm -rf "$dir"
        mkdir -p "$dir" || return 1
        for f in "$src"/*.zip "$src"/*.whl; do
            "$py" -m zipfile -e "$f" "$dir" || { echo "setup_peers: could not unpack $f" >&2; return 1; }
        done
        printf '%s' "$list" >"$dir/.unpacked"
        echo "setup_peers: unpacked $(echo "$list" | tr '\n' ' ')into $dir ($(du -sm "$dir" | cut -f1) MiB)" >&2
    fi
    case ":${PYTHONPATH:-}:" in
        *":$dir:"*) ;;
        *) export PYTHONPATH="$dir${PYTHONPATH:+:$PYTHONPATH}" ;;
    esac
    echo "export PYTHONPATH=$PYTHONPATH"
}
_tofpeers_setup
_tofpeers_rc=$?
unset -f _tofpeers_setup
# `return` when sourced, `exit` when run as a script.
return $_tofpeers_rc 2>/dev/null || exit $_tofpeers_rc
