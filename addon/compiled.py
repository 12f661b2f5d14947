"""numba in Blender's Python: the compiled CPU tracer (``tofcore.compiled``), installed on request.

tofcore traces with compiled kernels wherever numba imports (``tofcore.compiled.tracer.choose``) and falls back
to its NumPy tracer otherwise, with the reason in ``frame.stats["transport"]["tracer_reason"]``. numba is
not bundled in the extension zip (its wheels with llvmlite are ~64 MB per platform, docs/blender.md), so the
preferences offer "Install numba for the compiled tracer", as they offer CuPy (:mod:`.gpu`):

=================  =====================================================================================
what               how
=================  =====================================================================================
where it goes      :func:`site_packages_dir`: a folder of its own beside CuPy's in the extension's user folder
                   (``…/tof_camera/site-packages-numba``; an install replaces its folder as a whole, so
                   CuPy's and numba's never share one), appended to ``sys.path`` after Blender's packages.
which packages     numba and llvmlite (its compiler back end), at the release line tofcore's ``compiled``
                   extra pins (pyproject.toml), ``--no-deps`` so Blender's NumPy stays the only one; numba
                   0.68 supports NumPy 1.22–2.5 (Blender 4.2–5.0 ship 1.26).
compile            the kernels, once (30 s on a fast machine; 128–183 s on a busy 2-core one in Debian's
                   Blender 4.3, tests/blender_gui/numba_run.py), by a child process (``tofcore.compiled.
                   child_compile``) started right after the install (:func:`start_compiling`) or by the first
                   render; a render waits for it and Esc still cancels at once, the compile going on. The
                   machine code is cached in the user's cache folder (``~/.cache/tofcore/numba-<hash>``, the
                   hash naming the kernels' source: ``tofcore.compiled._target``), so later Blender sessions
                   and a reinstall of the same extension version load it in about a second.
which renders      every one the add-on makes: image textures, a World colour or an Environment Texture
                   (HDRI) as ambient light (``tofcore.compiled.setup.unsupported``; tests/blender_gui/
                   numba_run.py renders a textured scene under an HDRI World compiled). :func:`blender_reason`
                   names the Blender setting in the UI where tofcore gives a reason.
=================  =====================================================================================

The pip run, its staging folder and cancellation are :class:`.gpu.Installer`'s. Nothing here imports
``bpy`` at module level, nor numba: the status reads package metadata.
"""

from __future__ import annotations

import importlib.metadata
import os

#: Name of the add-on's numba folder inside its user folder.
SITE_PACKAGES = "site-packages-numba"

#: What "Install numba" installs: tofcore's ``compiled`` extra (pyproject.toml) and the llvmlite that numba
#: release requires (tests/addon/test_compiled_install.py checks both against the metadata).
REQUIREMENTS = ("numba>=0.68,<0.69", "llvmlite>=0.50,<0.51")


def site_packages_dir(package: str | None = None) -> str:
    """The add-on's numba folder (not created), beside :func:`.gpu.site_packages_dir`'s."""
    from . import gpu

    return os.path.join(os.path.dirname(gpu.site_packages_dir(package)), SITE_PACKAGES)


def numba_install_command(python: str, target: str, *, pip: list[str] | None = None) -> list[str]:
    """The command line that installs numba and llvmlite into folder ``target`` (binary wheels, no deps)."""
    pip = list(pip) if pip else [python, "-m", "pip"]
    return [*pip, "install", "--target", target, "--upgrade", "--no-deps", "--only-binary=:all:",
            "--no-input", "--disable-pip-version-check", "--progress-bar", "off", "--no-warn-script-location",
            *REQUIREMENTS]


def installed_numba() -> str | None:
    """The version of the numba importable now (from its metadata, numba not imported), or None."""
    try:
        return importlib.metadata.version("numba")
    except importlib.metadata.PackageNotFoundError:
        return None


_last: dict = {}  # the last finished render's tracer and reason (note_tracer)


def note_tracer(transport_stats: dict | None) -> None:
    """Remember which tracer a finished render used (``frame.stats["transport"]``), for :func:`status_line`."""
    stats = transport_stats or {}
    if stats.get("tracer"):
        _last.clear()
        _last.update(tracer=stats["tracer"], tracer_reason=stats.get("tracer_reason", ""))


def last_tracer() -> dict:
    """``{"tracer", "tracer_reason"}`` of the last finished render ({} before the first)."""
    return dict(_last)


#: What the status bar, the log and the report call the compile (tofcore.progress.COMPILE_TEXT's words).
COMPILE_TEXT = "compiling the tracer (once per install)"


def activity_status(camera: str, event: dict) -> str:
    """The status bar's text while a pass runs, from tofcore's ``activity`` event: the compile with its
    seconds, or the samples per pixel traced so far."""
    if event.get("stage") == "compile":
        return (f"ToF render of {camera!r}: {COMPILE_TEXT}, {event['seconds']:.0f} s… (Esc to cancel; the "
                f"compile goes on in the background)")
    return (f"ToF render of {camera!r}: pass {event['pass']}, {event['spp']:.1f}/{event['spp_max']} spp… "
            f"(Esc to cancel)")


def compile_text(transport_stats: dict | None) -> str:
    """For the final report: how the tracer was compiled first ('' when its kernels were cached)."""
    how = (transport_stats or {}).get("compile") or ""
    return f"{COMPILE_TEXT}: {how}" if how else ""


class ActivityLines:
    """``activity`` for a render in background mode (``blender -b``: no status bar): the status text as a
    line on stdout, at most every :data:`INTERVAL_S` seconds, and at once when the compile starts."""

    INTERVAL_S = 5.0

    def __init__(self, camera: str):
        self.camera = camera
        self._last = -float("inf")
        self._stage = None

    def __call__(self, event: dict) -> None:
        import time

        now = time.monotonic()
        if event.get("stage") != self._stage or now - self._last >= self.INTERVAL_S:
            print(activity_status(self.camera, event).split("… (Esc", 1)[0], flush=True)
            self._last = now
        self._stage = event.get("stage")


def first_status(camera: str, device: str) -> str:
    """The status bar's text while a render's first pass runs: a CPU render whose compiled kernels are not
    cached yet has them compiled first (minutes, by a child process that Esc leaves running for the next
    render: ``tofcore.compiled.child_compile``), which it says."""
    first = f"ToF render of {camera!r}: first pass… (Esc to cancel)"
    if device != "cpu":
        return first
    from tofcore import compiled

    if compiled.cpu_kernels_cached() is not False:
        return first
    return (f"ToF render of {camera!r}: {COMPILE_TEXT}, 30 s to 3 min (later renders load it in a second), "
            f"then the first pass… (Esc to cancel; the compile goes on in the background)")


def start_compiling() -> bool:
    """Compile the tracer's CPU kernels in a background process now (after numba was installed), unless
    they are cached; whether it compiles (``tofcore.compiled.child_compile.start``)."""
    from tofcore.compiled import child_compile

    return not child_compile.start() and child_compile.running()


def compiling() -> bool:
    """Whether the background compile of :func:`start_compiling` (or a render's) runs now; imports no numba."""
    import sys

    child_compile = sys.modules.get("tofcore.compiled.child_compile")
    return child_compile is not None and child_compile.running()


def compile_state() -> tuple[str, float, str] | None:
    """The background compile's ``(state, seconds, line)`` (``tofcore.compiled.child_compile.state``: running,
    done or failed), or None where none ran in this session; imports no numba."""
    import sys

    child_compile = sys.modules.get("tofcore.compiled.child_compile")
    return None if child_compile is None else child_compile.state()


def status_line(last_tracer: dict | None = None) -> tuple[str, str]:
    """(text, icon) of the compiled-tracer box: installed or not, and which tracer the last render used.

    ``last_tracer``: ``{"tracer", "tracer_reason"}`` of the last frame's ``stats["transport"]``, if any.
    """
    version = installed_numba()
    if version is None:
        return ("numba is not installed: renders use the NumPy tracer (Install numba for a compiled tracer, "
                "about 2× faster per core)", 'INFO')
    state = compile_state()
    if compiling():
        so_far = f", {state[1]:.0f} s…" if state is not None and state[0] == "running" else ""
        return (f"numba {version} installed: compiling the tracer in the background{so_far} (30 s to 3 min, once; "
                f"renders wait for it)", 'SORTTIME')
    if last_tracer and last_tracer.get("tracer") == "numpy":
        reason = blender_reason(last_tracer.get("tracer_reason") or "")
        return f"numba {version} installed, but the last render used NumPy: {reason}", 'INFO'
    if last_tracer and last_tracer.get("tracer") == "compiled":
        return f"Ready: numba {version}, the last render used the compiled tracer", 'CHECKMARK'
    if state is not None and state[0] == "done":
        return (f"Ready: numba {version}, the tracer compiled in the background in {state[1]:.0f} s (cached for "
                f"later renders)", 'CHECKMARK')
    if state is not None and state[0] == "failed":
        return (f"numba {version} installed, but compiling the tracer in the background failed: {state[2]}; the "
                f"first render compiles it", 'ERROR')
    return (f"numba {version} installed: the first render compiles the tracer (30 s to 3 min, cached for "
            f"later renders)", 'INFO')


def tracer_text(transport_stats: dict | None) -> str:
    """One line naming the tracer a frame used and why (``frame.stats["transport"]``), '' when unknown."""
    stats = transport_stats or {}
    tracer = stats.get("tracer")
    if tracer == "compiled":
        parallel = stats.get("parallel") or ""
        if parallel.startswith("numba threads: "):
            return f"Tracer: compiled (numba, {parallel[len('numba threads: '):]} threads)"
        return f"Tracer: compiled ({parallel})" if parallel else "Tracer: compiled"
    if tracer == "numpy":
        reason = blender_reason(stats.get("tracer_reason") or "")
        return f"Tracer: NumPy ({reason})" if reason else "Tracer: NumPy"
    return ""


#: tofcore's reasons for the NumPy tracer (``tracer_reason``'s start) → what to do about it in Blender.
BLENDER_REASONS = {
    "numba is not installed": "numba is not installed: Preferences > Add-ons > ToF Camera Simulator > Install numba",
}
"""Textures, an HDRI World and every preset's sensor trace compiled (tofcore.compiled.setup.unsupported):
what a Blender scene exports never sends a render to NumPy once numba is installed."""


def blender_reason(reason: str) -> str:
    """tofcore's ``tracer_reason`` with the Blender way around it, where there is one (:data:`BLENDER_REASONS`).

    tofcore's words name no Blender setting; where the add-on knows the Blender one, it says that instead.
    """
    for start, text in BLENDER_REASONS.items():
        if reason.startswith(start):
            return text
    return reason
