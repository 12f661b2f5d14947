"""addon/compiled.py without Blender: what "Install numba" installs, the status and tracer lines.

``addon/compiled.py`` imports no ``bpy`` (nor numba), so it is loaded here on its own, as
``test_cupy_install.py`` loads ``gpu.py``.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import sys
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]

_spec = importlib.util.spec_from_file_location("tof_addon_compiled", REPO_ROOT / "addon" / "compiled.py")
compiled = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = compiled
_spec.loader.exec_module(compiled)


def test_requirements_are_tofcores_compiled_extra_and_its_llvmlite():
    extra = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["compiled"]
    assert [r for r in compiled.REQUIREMENTS if r.startswith("numba")] == extra
    try:
        numba_requires = importlib.metadata.requires("numba") or []
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("numba is not installed here: its llvmlite requirement cannot be read")
    requirements = pytest.importorskip("packaging.requirements")
    llvmlite = next(requirements.Requirement(r) for r in numba_requires if r.startswith("llvmlite"))
    ours = requirements.Requirement(next(r for r in compiled.REQUIREMENTS if r.startswith("llvmlite")))
    installed = importlib.metadata.version("llvmlite")
    assert llvmlite.specifier.contains(installed, prereleases=True) and ours.specifier.contains(installed)


def test_install_command_installs_no_numpy():
    command = compiled.numba_install_command("py", "/t/site-packages-numba.partial")
    assert command[:4] == ["py", "-m", "pip", "install"]
    assert command[command.index("--target") + 1] == "/t/site-packages-numba.partial"
    for option in ("--upgrade", "--no-deps", "--only-binary=:all:", "--no-input"):
        assert option in command
    requirements = command[command.index("--no-warn-script-location") + 1:]
    assert requirements == list(compiled.REQUIREMENTS)
    assert not any(r.lower().startswith("numpy") for r in requirements), "Blender's NumPy must stay the only one"
    assert compiled.numba_install_command("py", "/t", pip=["py", "/w/pip"])[:3] == ["py", "/w/pip", "install"]


def test_tracer_text():
    assert compiled.tracer_text({"tracer": "compiled", "tracer_reason": "", "parallel": "numba threads: 8"}) == \
        "Tracer: compiled (numba, 8 threads)"
    assert compiled.tracer_text({"tracer": "compiled", "parallel": "CUDA (numba), one path per thread"}) == \
        "Tracer: compiled (CUDA (numba), one path per thread)"
    assert compiled.tracer_text({"tracer": "numpy", "tracer_reason": "TOFCORE_TRACER=numpy"}) == \
        "Tracer: NumPy (TOFCORE_TRACER=numpy)"
    # tofcore's hint (pip install "tofcore[compiled]") becomes the Blender way
    assert compiled.tracer_text({"tracer": "numpy", "tracer_reason": 'numba is not installed (pip install '
                                 '"tofcore[compiled]")'}) == ("Tracer: NumPy (numba is not installed: Preferences > "
                                                              "Add-ons > ToF Camera Simulator > Install numba)")
    assert compiled.tracer_text(None) == "" and compiled.tracer_text({}) == ""


def test_an_hdri_world_and_textures_render_compiled():
    """The World's Environment Texture (ambient light from an environment map) and textured materials no longer
    send a render to NumPy: tofcore's compiled tracer has no reason left for what the add-on exports."""
    import numpy as np

    from tofcore.compiled import setup

    ambient = SimpleNamespace(environment=np.ones((2, 4)), environment_strength=1.0)
    assert setup.unsupported(SimpleNamespace(ambient=ambient, transient_bins=0, correlations=[])) == ""
    assert compiled.blender_reason("TOFCORE_TRACER=numpy") == "TOFCORE_TRACER=numpy"   # others unchanged


def test_status_line(monkeypatch):
    monkeypatch.setattr(compiled, "installed_numba", lambda: None)
    text, icon = compiled.status_line()
    assert text.startswith("numba is not installed: renders use the NumPy tracer") and icon == 'INFO'
    monkeypatch.setattr(compiled, "installed_numba", lambda: "0.68.1")
    assert compiled.status_line()[0].startswith("numba 0.68.1 installed: the first render compiles the tracer")
    monkeypatch.setattr(compiled, "_last", {})
    compiled.note_tracer({"tracer": "compiled", "tracer_reason": "", "parallel": "numba threads: 2"})
    assert compiled.status_line(compiled.last_tracer()) == (
        "Ready: numba 0.68.1, the last render used the compiled tracer", 'CHECKMARK')
    compiled.note_tracer({})                                     # a frame without tracer stats changes nothing
    assert compiled.last_tracer()["tracer"] == "compiled"
    compiled.note_tracer({"tracer": "numpy", "tracer_reason": "correlation channel 0 (<lambda>) is Python code "
                                                              "the compiled tracer cannot run"})
    assert compiled.status_line(compiled.last_tracer())[0].startswith(
        "numba 0.68.1 installed, but the last render used NumPy: correlation channel 0 (<lambda>) is Python code")


def test_first_status_says_a_cold_cpu_render_compiles_first(monkeypatch):
    """The status bar before the first pass: the compile (in a child process that Esc leaves running) only
    for a CPU render whose kernels are not cached; a cached, GPU or NumPy-only render shows the plain
    first-pass line."""
    from tofcore import compiled as tof_compiled

    plain = "ToF render of 'Cam': first pass… (Esc to cancel)"
    for cached, device, expected_compile in ((False, "cpu", True), (True, "cpu", False), (None, "cpu", False),
                                             (False, "gpu", False), (False, "auto", False)):
        monkeypatch.setattr(tof_compiled, "cpu_kernels_cached", lambda cached=cached: cached)
        text = compiled.first_status("Cam", device)
        says_compile = "compiling the tracer (once per install)" in text and "the compile goes on in the background" in text
        assert says_compile == expected_compile
        assert (text == plain) == (not expected_compile)


def test_the_status_says_the_background_compile_runs(monkeypatch):
    """After Install numba the tracer compiles in a child process; the box says so while it runs."""
    from tofcore.compiled import child_compile

    monkeypatch.setattr(compiled, "installed_numba", lambda: "0.68.1")
    monkeypatch.setattr(child_compile, "running", lambda: True)
    text, icon = compiled.status_line({})
    assert text.startswith("numba 0.68.1 installed: compiling the tracer in the background") and icon == 'SORTTIME'
    monkeypatch.setattr(child_compile, "running", lambda: False)
    assert "background" not in compiled.status_line({})[0]


def test_the_status_says_how_the_background_compile_ended(monkeypatch):
    """While the compile after Install numba runs, its seconds; then ready in N s, or failed: one line."""
    from tofcore.compiled import child_compile

    monkeypatch.setattr(compiled, "installed_numba", lambda: "0.68.1")
    monkeypatch.setattr(child_compile, "running", lambda: True)
    monkeypatch.setattr(child_compile, "state", lambda: ("running", 12.3, ""))
    assert compiled.status_line({})[0] == ("numba 0.68.1 installed: compiling the tracer in the background, 12 s… "
                                           "(30 s to 3 min, once; renders wait for it)")
    monkeypatch.setattr(child_compile, "running", lambda: False)
    monkeypatch.setattr(child_compile, "state", lambda: ("done", 41.6, ""))
    assert compiled.status_line({}) == ("Ready: numba 0.68.1, the tracer compiled in the background in 42 s (cached "
                                        "for later renders)", 'CHECKMARK')
    monkeypatch.setattr(child_compile, "state", lambda: ("failed", 3.0, "`python -m tofcore warmup --device cpu` "
                                                                        "ended with exit status 1: MemoryError"))
    text, icon = compiled.status_line({})
    assert icon == 'ERROR' and text == ("numba 0.68.1 installed, but compiling the tracer in the background failed: "
                                        "`python -m tofcore warmup --device cpu` ended with exit status 1: "
                                        "MemoryError; the first render compiles it")
    compiled.note_tracer({"tracer": "compiled"})                 # a render since: it says what that render used
    assert compiled.status_line(compiled.last_tracer())[0].startswith("Ready: numba 0.68.1, the last render used")


def test_the_status_bar_and_the_report_say_the_compile_and_the_pass_inside(capsys):
    """While the first render compiles, the status bar says so with its seconds (tofcore's ``activity``); the
    final report says how long it took; in background mode the same words are printed (issue 36)."""
    from tofcore.progress import COMPILE_TEXT

    assert compiled.COMPILE_TEXT == COMPILE_TEXT  # the add-on and the command line use the same words
    text = compiled.activity_status("Cam", {"stage": "compile", "seconds": 41.6})
    assert text.startswith("ToF render of 'Cam': compiling the tracer (once per install), 42 s…")
    assert compiled.activity_status("Cam", {"stage": "trace", "pass": 1, "spp": 6.25, "spp_max": 16}) \
        .startswith("ToF render of 'Cam': pass 1, 6.2/16 spp…")
    assert compiled.compile_text({"compile": "compiled by a child process in 95.3 s"}) == \
        "compiling the tracer (once per install): compiled by a child process in 95.3 s"
    assert compiled.compile_text({"compile": ""}) == compiled.compile_text(None) == ""
    lines = compiled.ActivityLines("Cam")
    for seconds in (0.0, 0.5, 1.0):
        lines({"stage": "compile", "seconds": seconds})
    lines({"stage": "trace", "pass": 1, "spp": 1.0, "spp_max": 16})
    assert capsys.readouterr().out.splitlines() == [
        "ToF render of 'Cam': compiling the tracer (once per install), 0 s", "ToF render of 'Cam': pass 1, 1.0/16 spp"]
