"""Add-on preferences: the device switch, the GPU box, "Install CuPy for GPU rendering", "Check GPU" and
"Install numba for the compiled tracer".

Runs in the PyPI ``bpy`` module. Nothing is downloaded: the installer's pip is replaced by a stand-in
(this Python printing what pip prints and writing a CuPy dist-info), whose command line is otherwise
the real one (:func:`addon.gpu.cupy_install_command`, tested in ``test_cupy_install.py``).
"""

from __future__ import annotations

import os
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root: `import addon`
from tests import fakecupy  # noqa: E402  (the CuPy stand-in)

import addon  # noqa: E402
from addon_helpers import Reports  # noqa: E402
from addon import compiled, gpu, preferences  # noqa: E402




@pytest.fixture
def prefs(clean_bpy, monkeypatch, tmp_path):
    """The add-on registered and enabled (its real preferences); CuPy's folder is a temporary one."""
    folder = str(tmp_path / "site-packages")
    monkeypatch.setattr(preferences, "cupy_folder", lambda: folder)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(gpu, "_status", None)
    addon.register()
    entry = bpy.context.preferences.addons.new()
    entry.module = "addon"
    yield entry.preferences
    bpy.context.preferences.addons.remove(entry)
    addon.unregister()


def run_execute(operator_class, context=None):
    """``operator_class.execute`` on a stand-in operator that collects its reports: (result, Reports)."""
    op = SimpleNamespace(report=Reports(), what=getattr(operator_class, "what", ""))
    for name in ("execute", "_start", "prepare", "finish"):
        if hasattr(operator_class, name):
            setattr(op, name, getattr(operator_class, name).__get__(op))
    return op.execute(context or bpy.context), op.report


# --------------------------------------------------------------------------- the properties

def test_device_preference(prefs):
    rna = preferences.TofPreferences.bl_rna.properties
    device = rna["device"]
    assert device.default == 'cpu' and prefs.device == 'cpu'
    assert [(item.identifier, item.name) for item in device.enum_items] == [
        ('cpu', "CPU"), ('gpu', "GPU (CUDA, CuPy)"), ('auto', "Auto")]
    assert all(item.description for item in device.enum_items)
    package = rna["cupy_package"]
    assert package.default == 'cupy-cuda12x' and prefs.cupy_package == 'cupy-cuda12x'
    assert [(item.identifier, item.name) for item in package.enum_items] == [
        ('cupy-cuda12x', "CUDA 12 (driver ≥ 525)"), ('cupy-cuda13x', "CUDA 13 (driver ≥ 580)")]
    assert "580" in package.enum_items['cupy-cuda13x'].description
    # Not enabled through Blender's add-on system (the other tests): the defaults.
    assert preferences._DEFAULTS.device == 'cpu' and preferences._DEFAULTS.cupy_package == 'cupy-cuda12x'


def test_registration_neither_imports_cupy_nor_creates_folders(clean_bpy, monkeypatch, tmp_path):
    monkeypatch.setattr(sys, "path", list(sys.path))
    imported = "cupy" in sys.modules
    folder = tmp_path / "site-packages"
    monkeypatch.setattr(preferences, "cupy_folder", lambda: str(folder))
    addon.register()
    assert str(folder) not in sys.path and not folder.exists()
    addon.unregister()
    folder.mkdir()                               # CuPy installed earlier: importable after registration
    addon.register()
    assert sys.path[-1] == str(folder)
    assert ("cupy" in sys.modules) == imported
    addon.unregister()
    assert str(folder) not in sys.path


def test_cupy_folder_is_the_extension_user_folder():
    pytest.importorskip("bpy")
    folder = gpu.site_packages_dir("bl_ext.user_default.tof_camera")
    assert folder == bpy.utils.extension_path_user("bl_ext.user_default.tof_camera", path="site-packages")
    assert os.path.join("extensions", ".user", "user_default", "tof_camera", "site-packages") in folder
    # The plain package the tests load is no extension: a folder of the user's datafiles.
    assert gpu.site_packages_dir("addon").endswith(os.path.join("tof_camera", "site-packages"))


class RecordingLayout:
    """Stands in for ``UILayout``: checks every property and operator drawn exists; keeps the labels."""

    def __init__(self, log: list) -> None:
        object.__setattr__(self, "log", log)

    def __getattr__(self, name):  # row(), column(), box(), separator() …
        return lambda *args, **kwargs: self

    def __setattr__(self, name, value):  # use_property_split …
        pass

    def label(self, text="", icon='NONE', **kwargs):
        self.log.append(("label", text, icon))
        return self

    def prop(self, data, name, **kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.log.append(("prop", name, None))
        return self

    def operator(self, idname, **kwargs):
        module, _, op = idname.partition(".")
        assert hasattr(getattr(bpy.ops, module), op), f"no operator {idname!r}"
        self.log.append(("operator", idname, None))
        return self


def test_preferences_draw_gpu_box(prefs):
    log: list = []
    assert gpu._status is None                   # nothing computed before the preferences are drawn
    preferences.TofPreferences.draw(SimpleNamespace(layout=RecordingLayout(log), bl_rna=prefs.bl_rna), bpy.context)
    drawn = [name for kind, name, _ in log if kind in ("prop", "operator")]
    assert drawn == ["default_output_dir", "workers", "preview_delay_s", "device", "tof.install_numba",
                     "cupy_package", "tof.install_cupy", "tof.check_gpu"]
    labels = [(text, icon) for kind, text, icon in log if kind == "label"]
    labels = labels[labels.index(("GPU (CuPy)", 'SETTINGS')):]          # the GPU box (the numba box first)
    if not gpu.installed_cupy() and gpu.platform_problem() is None:
        assert labels[1] == ("CuPy is not installed in Blender's Python: GPU rendering needs it (Install CuPy for "
                             "GPU rendering)", 'INFO')
    assert gpu._status is not None               # computed once, then cached
    assert labels[-1][0] == f"Installs into {preferences.cupy_folder()}"
    # A long status wraps over several labels (Blender's labels do not wrap).
    gpu.status().problem = "GPU: " + "x " * 150
    gpu.status().cupy = [("cupy-cuda12x", "13.6.0", "/x")]
    log.clear()
    preferences.draw_gpu(prefs, RecordingLayout(log))
    status = [(text, icon) for kind, text, icon in log if kind == "label"][1:-1]
    assert len(status) >= 3 and status[0][1] == 'ERROR' and {icon for _, icon in status[1:]} == {'BLANK1'}
    assert all(len(text) <= preferences.STATUS_WIDTH for text, _ in status)


# --------------------------------------------------------------------------- Install CuPy for GPU rendering

def test_install_refused_when_offline(prefs):
    if bpy.app.online_access:
        pytest.skip("online access is on: this test never downloads")
    result, reports = run_execute(preferences.TOF_OT_install_cupy)
    assert result == {'CANCELLED'}
    assert reports.of("ERROR") == ["Cannot install CuPy: Online access is off: allow it in Preferences > System > "
                                   "Network > Allow Online Access, or install CuPy by hand (docs/blender.md, GPU in "
                                   "Blender)"]
    with pytest.raises(RuntimeError, match="Cannot install CuPy: Online access is off") as raised:
        bpy.ops.tof.install_cupy()
    assert "Traceback" not in str(raised.value)
    assert not os.path.exists(preferences.cupy_folder())


FAKE_PIP = """
import os, sys
target = sys.argv[sys.argv.index("--target") + 1]
requirements = sys.argv[sys.argv.index("--no-warn-script-location") + 1:]
print("Collecting " + requirements[0], flush=True)
if "--no-deps" not in sys.argv or not target.endswith(".partial"):
    print("ERROR: unexpected command line"); sys.exit(3)
if requirements[0].startswith("cupy-cuda13x"):
    print("ERROR: Could not find a version that satisfies the requirement " + requirements[0])
    print("ERROR: No matching distribution found for cupy-cuda13x"); sys.exit(1)
info = os.path.join(target, "cupy_cuda12x-13.6.0.dist-info")
os.makedirs(info)
with open(os.path.join(info, "METADATA"), "w") as fh:
    fh.write("Metadata-Version: 2.1\\nName: cupy-cuda12x\\nVersion: 13.6.0\\n")
print("Successfully installed cupy-cuda12x-13.6.0 fastrlock-0.8.4", flush=True)
"""


@pytest.fixture
def fake_pip(prefs, monkeypatch, tmp_path):
    """Online, and pip replaced by a stand-in; returns the command lines the operator built."""
    script = tmp_path / "fake_pip.py"
    script.write_text(textwrap.dedent(FAKE_PIP), encoding="utf-8")
    commands = []
    real = gpu.cupy_install_command

    def command(python, target, package, **kwargs):
        assert python == sys.executable and kwargs["pip"] == [sys.executable, "-m", "pip"]
        line = real(python, target, package, **kwargs)
        commands.append(line)
        return [sys.executable, str(script), *line[3:]]       # pip's arguments, the stand-in's program

    monkeypatch.setattr(preferences, "_online_problem", lambda what: None)
    monkeypatch.setattr(gpu, "cupy_install_command", command)
    return commands


def test_install_runs_pip_into_the_folder(prefs, fake_pip):
    folder = preferences.cupy_folder()
    result, reports = run_execute(preferences.TOF_OT_install_cupy)
    assert result == {'FINISHED'}, reports.items
    (command,) = fake_pip
    assert command[command.index("--target") + 1] == folder + ".partial"
    assert any(r.startswith("cupy-cuda12x") for r in command)
    assert os.listdir(folder) == ["cupy_cuda12x-13.6.0.dist-info"] and not os.path.exists(folder + ".partial")
    assert sys.path[-1] == folder
    assert [name for name, _, _ in gpu.status().cupy] == ["cupy-cuda12x"]
    if "cupy" not in sys.modules:   # a dist-info without the module: the check after installing says so
        (warning,) = reports.of("WARNING")
        assert warning.startswith("Successfully installed cupy-cuda12x-13.6.0 fastrlock-0.8.4, but the GPU "
                                  "cannot run: GPU: CuPy is not installed")
    assert not reports.of("ERROR")


def test_install_failure_reports_pips_reason(prefs, fake_pip):
    prefs.cupy_package = 'cupy-cuda13x'
    result, reports = run_execute(preferences.TOF_OT_install_cupy)
    assert result == {'CANCELLED'}
    assert reports.of("ERROR") == ["Installing CuPy failed: No matching distribution found for cupy-cuda13x"]
    assert any(r.startswith("cupy-cuda13x") for r in fake_pip[0])
    assert not os.path.exists(preferences.cupy_folder())
    with pytest.raises(RuntimeError, match="Installing CuPy failed: No matching distribution") as raised:
        bpy.ops.tof.install_cupy()
    assert "Traceback" not in str(raised.value)


def test_install_in_worker_thread_like_the_ui(prefs, fake_pip):
    """What ``invoke`` runs: the installer in a thread, polled, then the same ending."""
    installer = preferences.prepare_install(prefs.cupy_package, Reports())
    installer.start()
    installer.join(60)
    assert installer.state == "done"
    reports = Reports()
    assert preferences.finish_install(installer, reports) == {'FINISHED'}
    assert not reports.of("ERROR")


def test_after_installing_cupy_the_gpu_kernels_warm_up_in_the_background(prefs, fake_pip, monkeypatch):
    """A successful install whose GPU answers starts ``tofcore warmup --device gpu`` in a child process (not in
    this one) and returns at once; the GPU box then shows the warm-up's state."""
    started = []
    monkeypatch.delitem(sys.modules, "cupy", raising=False)  # this session runs no older CuPy
    monkeypatch.setattr(gpu, "check", lambda folder: SimpleNamespace(device="GPU 0: fake", problem=None))
    monkeypatch.setattr(gpu, "start_warmup", lambda folder, python=None: started.append(folder))
    result, reports = run_execute(preferences.TOF_OT_install_cupy)
    assert result == {'FINISHED'}, reports.items
    assert started == [preferences.cupy_folder()]
    assert reports.of("INFO") == ["Successfully installed cupy-cuda12x-13.6.0 fastrlock-0.8.4; GPU ready: GPU 0: "
                                  "fake; warming up its kernels in the background (compiled once)"]


def test_the_gpu_box_shows_the_warm_up(prefs, monkeypatch):
    warmup = gpu.Warmup(["py", "-c", "pass"])
    monkeypatch.setattr(gpu, "_warmup", warmup)
    log: list = []

    def drawn() -> tuple[str, set]:
        """The GPU box's labels as one text (long lines wrap over several labels), and their icons."""
        log.clear()
        preferences.draw_gpu(prefs, RecordingLayout(log))
        labels = [(text, icon) for kind, text, icon in log if kind == "label"]
        return " ".join(text for text, _ in labels), {icon for _, icon in labels}

    warmup._started, warmup._ended = 0.0, 31.4
    text, icons = drawn()
    assert ("Warming up the GPU kernels in the background: 31 s… (compiled once; a render meanwhile compiles "
            "what it needs itself)") in text and 'SORTTIME' in icons
    warmup.state = "done"
    text, icons = drawn()
    assert "GPU kernels ready in 31 s (compiled once, cached for later renders)" in text and 'CHECKMARK' in icons
    warmup.state, warmup.message = "error", "exit status 2: error: --device gpu: no usable GPU"
    text, icons = drawn()
    assert ("GPU kernel warm-up failed: exit status 2: error: --device gpu: no usable GPU; the first GPU render "
            "compiles them") in text and 'ERROR' in icons
    monkeypatch.setattr(gpu, "_warmup", None)
    assert "warm-up" not in drawn()[0] and "Warming" not in drawn()[0]          # none started


# --------------------------------------------------------------------------- Check GPU

def test_check_gpu_without_cupy(prefs, monkeypatch):
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [])
    result, reports = run_execute(preferences.TOF_OT_check_gpu)
    assert result == {'FINISHED'}
    assert reports.of("WARNING") == ["CuPy is not installed in Blender's Python: GPU rendering needs it "
                                     "(Install CuPy for GPU rendering)"]


def test_check_gpu_on_stand_in(prefs, monkeypatch):
    fakecupy.install(monkeypatch)
    monkeypatch.setattr(gpu, "installed_cupy", lambda: [("cupy-cuda12x", "fake", "/x")])
    result, reports = run_execute(preferences.TOF_OT_check_gpu)
    assert result == {'FINISHED'}
    assert reports.of("INFO") == ["GPU ready: fake GPU (NumPy behind CuPy's rules)"]
    assert gpu.status().line() == ("Ready: fake GPU (NumPy behind CuPy's rules)", 'CHECKMARK')


# --------------------------------------------------------------------------- Install numba for the compiled tracer

FAKE_NUMBA_PIP = """
import os, sys
target = sys.argv[sys.argv.index("--target") + 1]
requirements = sys.argv[sys.argv.index("--no-warn-script-location") + 1:]
print("Collecting " + requirements[0], flush=True)
if "--no-deps" not in sys.argv or not target.endswith(".partial"):
    print("ERROR: unexpected command line"); sys.exit(3)
for name in ("numba-0.68.1", "llvmlite-0.50.0"):
    os.makedirs(os.path.join(target, name + ".dist-info"))
print("Successfully installed llvmlite-0.50.0 numba-0.68.1", flush=True)
"""


@pytest.fixture
def numba_pip(prefs, monkeypatch, tmp_path):
    """numba's folder a temporary one, online, pip replaced by a stand-in; returns the command lines built."""
    folder = str(tmp_path / "site-packages-numba")
    monkeypatch.setattr(preferences, "numba_folder", lambda: folder)
    script = tmp_path / "fake_numba_pip.py"
    script.write_text(textwrap.dedent(FAKE_NUMBA_PIP), encoding="utf-8")
    commands = []
    real = compiled.numba_install_command

    def command(python, target, **kwargs):
        assert python == sys.executable and kwargs["pip"] == [sys.executable, "-m", "pip"]
        line = real(python, target, **kwargs)
        commands.append(line)
        return [sys.executable, str(script), *line[3:]]

    monkeypatch.setattr(preferences, "_online_problem", lambda what: None)
    monkeypatch.setattr(compiled, "numba_install_command", command)
    return commands


def test_install_numba_runs_pip_into_its_own_folder(prefs, numba_pip):
    folder = preferences.numba_folder()
    result, reports = run_execute(preferences.TOF_OT_install_numba)
    assert result == {'FINISHED'}, reports.items
    (command,) = numba_pip
    assert command[command.index("--target") + 1] == folder + ".partial"
    assert command[-2:] == list(compiled.REQUIREMENTS)
    assert sorted(os.listdir(folder)) == ["llvmlite-0.50.0.dist-info", "numba-0.68.1.dist-info"]
    assert sys.path[-1] == folder and folder != preferences.cupy_folder()
    assert not reports.of("ERROR")
    message = reports.of("WARNING" if "numba" in sys.modules else "INFO")
    assert message[0].startswith("Successfully installed llvmlite-0.50.0 numba-0.68.1")


def test_install_numba_refused_when_offline(prefs, monkeypatch, tmp_path):
    monkeypatch.setattr(preferences, "numba_folder", lambda: str(tmp_path / "numba"))
    if bpy.app.online_access:
        pytest.skip("online access is on: this test never downloads")
    result, reports = run_execute(preferences.TOF_OT_install_numba)
    assert result == {'CANCELLED'}
    assert reports.of("ERROR") == ["Cannot install numba: Online access is off: allow it in Preferences > System > "
                                   "Network > Allow Online Access, or install numba by hand (docs/blender.md, The "
                                   "compiled tracer)"]
    assert not (tmp_path / "numba").exists()


def test_install_numba_without_pip_points_to_its_own_readme_section(prefs, monkeypatch, tmp_path):
    """Debian's Blender 4.3 (Python 3.13 without pip or ensurepip) answered "install numba by hand (README, GPU
    in Blender)": the CuPy section. The by-hand pointer is the package's own."""
    monkeypatch.setattr(preferences, "numba_folder", lambda: str(tmp_path / "numba"))
    monkeypatch.setattr(preferences, "_online_problem", lambda what: None)
    monkeypatch.setattr(gpu, "run_quiet", lambda command, timeout_s: SimpleNamespace(returncode=1))
    monkeypatch.setattr(gpu, "bundled_pip_wheel", lambda: None)
    for operator, what, section in ((preferences.TOF_OT_install_numba, "numba", "The compiled tracer"),
                                    (preferences.TOF_OT_install_cupy, "CuPy", "GPU in Blender")):
        if what == "CuPy" and gpu.platform_problem():
            continue
        result, reports = run_execute(operator)
        assert result == {'CANCELLED'}
        assert reports.of("ERROR") == [f"Cannot install {what}: pip is not available in Blender's Python "
                                       f"({sys.executable}) and ensurepip has no pip wheel; install {what} by hand "
                                       f"(docs/blender.md, {section})"]
    assert not (tmp_path / "numba").exists()


def test_one_install_at_a_time(prefs, numba_pip):
    installer = preferences.prepare_numba_install(Reports())
    preferences._install.installer, preferences._install.what = installer, "numba"
    try:
        assert not preferences.TOF_OT_install_cupy.poll(bpy.context) or gpu.platform_problem()
        assert preferences.TOF_OT_install_cupy.install_problem() in ("numba is being installed (Esc cancels)",
                                                                     gpu.platform_problem())
        assert preferences.compiled_status_line()[1] == 'SORTTIME'
        assert preferences.status_line()[1] != 'SORTTIME'          # the GPU box is not the one installing
    finally:
        preferences._install.installer = None


def test_preferences_draw_numba_box(prefs, monkeypatch):
    from tofcore.compiled import child_compile

    monkeypatch.setattr(compiled, "_last", {})
    monkeypatch.setattr(child_compile, "_child", {})  # no background compile of an earlier test in this process
    log: list = []
    preferences.draw_compiled(RecordingLayout(log))
    labels = [(text, icon) for kind, text, icon in log if kind == "label"]
    assert labels[0] == ("Compiled CPU tracer (numba)", 'SETTINGS')
    assert labels[-1][0] == f"Installs into {preferences.numba_folder()}"
    assert ("operator", "tof.install_numba", None) in log
    version = compiled.installed_numba()
    status = " ".join(text for text, _ in labels[1:-1])
    if version is None:
        assert status.startswith("numba is not installed: renders use the NumPy tracer")
    else:
        assert status.startswith(f"numba {version} installed: the first render compiles the tracer")
        compiled.note_tracer({"tracer": "numpy", "tracer_reason": "ambient light (the compiled tracer has none)"})
        assert compiled.status_line(compiled.last_tracer()) == (
            f"numba {version} installed, but the last render used NumPy: ambient light (the compiled tracer has "
            f"none)", 'INFO')


def test_numba_folder_beside_cupys():
    assert compiled.site_packages_dir("addon") == os.path.join(os.path.dirname(gpu.site_packages_dir("addon")),
                                                               "site-packages-numba")
