#!/usr/bin/env bash
# Run a script inside a REAL Blender GUI (Debian 13's Blender 4.3.2, Python 3.13) on a virtual display, with an
# extension zip installed, and copy back what it wrote. Needs root (chroot) and, on the first run only, Debian's
# package mirror. Adapted from the project's shared tool; each run has its own folder and display, so several
# runs (several engineers) can share one root.
#
#   tests/blender_gui/real_blender.sh dist/tof_camera-0.1.0.zip SCRIPT OUTDIR [--background]
#
# The first run builds a Debian 13 (trixie) root at $ROOT (default /opt/blender-trixie, ~1.9 GB, ~3 min) with
# blender, xvfb, x11-apps and imagemagick; later runs reuse it. Inside Blender the script finds the zip installed
# as extension "bl_ext.user_default.<id>", env TOF_GUI_OUT (a folder copied back to OUTDIR) and SCREENSHOT_CMD
# (a shell command saving the whole screen to $TOF_GUI_OUT/screen-N.png; bpy.ops.screen.screenshot gives black
# images on this software-GL display). $BLENDER_ARGS go on Blender's command line (e.g. --enable-event-simulate).
# The splash screen is turned off. Exit code: the script's (124: it ran past $TIMEOUT seconds, default 600).
set -euo pipefail
[ $# -ge 3 ] || { echo "usage: $0 ZIP SCRIPT OUTDIR [--background]" >&2; exit 2; }
zip=$(readlink -f "$1"); script=$(readlink -f "$2"); out=$(readlink -m "$3"); mode=${4:-}
ROOT=${ROOT:-/opt/blender-trixie}
[ "$(id -u)" = 0 ] || { echo "$0: needs root (chroot into $ROOT)" >&2; exit 2; }
if [ ! -x "$ROOT/usr/bin/blender" ]; then
  command -v debootstrap >/dev/null || { apt-get update -qq && apt-get install -y -qq debootstrap; }
  debootstrap --variant=minbase --include=blender,xvfb,xauth,x11-apps,imagemagick,python3-numpy \
    trixie "$ROOT" http://deb.debian.org/debian >/tmp/real-blender-debootstrap.log 2>&1 \
    || { echo "debootstrap failed: see /tmp/real-blender-debootstrap.log"; exit 1; }
fi
mountpoint -q "$ROOT/proc" || mount --bind /proc "$ROOT/proc"
mountpoint -q "$ROOT/dev" || mount --bind /dev "$ROOT/dev"
run_id=tof-gui-$$
work=/$run_id                                  # inside the root
display=$(( 100 + $$ % 400 ))
rm -rf "$ROOT$work"; mkdir -p "$ROOT$work/out" "$ROOT/tmp/.X11-unix"; chmod 1777 "$ROOT/tmp" "$ROOT/tmp/.X11-unix"
trap 'rm -rf "$ROOT$work"' EXIT
cp "$zip" "$ROOT$work/ext.zip"; cp "$script" "$ROOT$work/test.py"
cat > "$ROOT$work/run.sh" <<INNER
set -u
export HOME=$work TOF_GUI_OUT=$work/out
cd $work
blender -b --factory-startup --command extension install-file -r user_default -e $work/ext.zip >$work/out/install.log 2>&1 \
  || { echo "extension install failed"; cat $work/out/install.log; exit 3; }
# No splash screen over the UI in the screenshots.
blender -b --python-expr 'import bpy; bpy.context.preferences.view.show_splash = False; bpy.ops.wm.save_userpref()' \
  >>$work/out/install.log 2>&1
if [ "\${MODE:-}" = "--background" ]; then
  timeout "\${TIMEOUT:-600}" blender -b --python $work/test.py >$work/out/blender.log 2>&1; rc=\$?
else
  Xvfb :$display -screen 0 1600x1000x24 -nolisten tcp >$work/out/xvfb.log 2>&1 & xpid=\$!
  sleep 2
  export DISPLAY=:$display
  export SCREENSHOT_CMD='n=\$(ls $work/out/screen-*.png 2>/dev/null | wc -l); xwd -root -display :$display -silent | convert xwd:- $work/out/screen-\$n.png'
  timeout "\${TIMEOUT:-600}" blender \${BLENDER_ARGS:-} --python $work/test.py >$work/out/blender.log 2>&1; rc=\$?
  kill \$xpid 2>/dev/null
fi
[ /tmp/blender.crash.txt -nt $work/test.py ] && cp /tmp/blender.crash.txt $work/out/   # Blender's backtrace
exit \$rc
INNER
set +e
env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin LANG=C.UTF-8 MODE="$mode" TIMEOUT="${TIMEOUT:-600}" BLENDER_ARGS="${BLENDER_ARGS:-}" \
  chroot "$ROOT" /bin/bash "$work/run.sh"; rc=$?   # a clean environment: nothing of the caller's venv leaks in
set -e
rm -rf "$out"; mkdir -p "$out"; cp -r "$ROOT$work/out/." "$out/"
echo "real Blender exited $rc; its log, screenshots and outputs are in $out"
exit $rc
