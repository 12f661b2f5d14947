"""addon/gpu.py without Blender: the pip command, the CUDA library files, the installer, the status text.

``addon/gpu.py`` imports no ``bpy`` at module level, so it is loaded here on its own (as
``test_package.py`` loads ``build.py``) and these tests run without the bpy module. Nothing is
downloaded: the installer runs stand-ins for pip (this Python printing what pip prints).
"""

from __future__ import annotations

import importlib.util
import os
import sys
import textwrap
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]

_spec = importlib.util.spec_from_file_location("tof_addon_gpu", REPO_ROOT / "addon" / "gpu.py")
gpu = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = gpu            # dataclasses look their module up by name
_spec.loader.exec_module(gpu)

PIP = ["/blender/5.0/python/bin/python3.11", "-m", "pip"]


# --------------------------------------------------------------------------- the pip command

def test_install_command_blender_5_0_numpy_1():
    """Blender 4.2-5.0 (NumPy 1.26): CuPy 13 with fastrlock; CUDA 12 libraries; nothing resolves NumPy."""
    command = gpu.cupy_install_command(PIP[0], "/user/tof_camera/site-packages", "cupy-cuda12x",
                                       numpy_version="1.26.4")
    assert command[:4] == [*PIP, "install"]
    assert command[command.index("--target") + 1] == "/user/tof_camera/site-packages"
    for option in ("--upgrade", "--no-deps", "--only-binary=:all:", "--no-input", "--disable-pip-version-check"):
        assert option in command, option
    assert command[command.index("--progress-bar") + 1] == "off"
    requirements = command[command.index("--no-warn-script-location") + 1:]
    assert requirements == ["cupy-cuda12x>=13.3,<14", "fastrlock>=0.5", "nvidia-cuda-nvrtc-cu12==12.*",
                            "nvidia-cublas-cu12==12.*", "nvidia-cufft-cu12==11.*", "nvidia-nvjitlink-cu12==12.*"]
    assert not any(r.lower().startswith("numpy") for r in requirements), "Blender's NumPy must stay the only one"


def test_install_command_blender_5_1_numpy_2_cuda_13():
    """Blender 5.1+ (NumPy 2): CuPy 14 with cuda-pathfinder; CUDA 13 libraries (no -cu13 suffix)."""
    command = gpu.cupy_install_command("python3.13", "/t", "cupy-cuda13x", numpy_version="2.3.1")
    requirements = command[command.index("--no-warn-script-location") + 1:]
    assert requirements == ["cupy-cuda13x>=14,<15", "cuda-pathfinder>=1.3.4,<2", "nvidia-cuda-nvrtc==13.*",
                            "nvidia-cublas==13.*", "nvidia-cufft==12.*", "nvidia-nvjitlink==13.*"]


def test_install_command_defaults_and_pip_override():
    import numpy

    command = gpu.cupy_install_command("py", "/t", "cupy-cuda12x")
    expected = "cupy-cuda12x>=14,<15" if int(numpy.__version__.split(".")[0]) >= 2 else "cupy-cuda12x>=13.3,<14"
    assert expected in command                                   # this process's NumPy picks the CuPy line
    bundled = ["py", "/lib/ensurepip/_bundled/pip-24.0-py3-none-any.whl/pip"]
    assert gpu.cupy_install_command("py", "/t", "cupy-cuda12x", pip=bundled)[:3] == [*bundled, "install"]
    with pytest.raises(gpu.InstallError, match=r"cupy_package must be one of \['cupy-cuda12x', 'cupy-cuda13x'\], "
                                               r"got 'cupy-cuda11x'"):
        gpu.cupy_install_command("py", "/t", "cupy-cuda11x", numpy_version="1.26.4")


def test_requirements_are_valid_pep508():
    requirements = pytest.importorskip("packaging.requirements")
    for line in gpu.CUDA_LINES:
        for numpy_version in ("1.26.4", "2.2.0"):
            for text in gpu.cupy_requirements(line.package, numpy_version):
                requirements.Requirement(text)


def test_cuda_lines_labels_name_driver():
    assert [line.package for line in gpu.CUDA_LINES] == ["cupy-cuda12x", "cupy-cuda13x"]
    assert gpu.DEFAULT_PACKAGE == "cupy-cuda12x"
    assert [line.label for line in gpu.CUDA_LINES] == ["CUDA 12 (driver ≥ 525)", "CUDA 13 (driver ≥ 580)"]


def test_pip_command_in_this_python():
    assert gpu.pip_command(sys.executable) == [sys.executable, "-m", "pip"]
    with pytest.raises(gpu.InstallError, match="pip is not available"):
        gpu.pip_command(str(REPO_ROOT / "no-such-python"))


def test_bundled_pip_wheel_runs_without_installing(tmp_path):
    wheel = gpu.bundled_pip_wheel()
    if wheel is None:
        pytest.skip("this Python's ensurepip bundles no pip wheel")
    proc = gpu.run_quiet([sys.executable, os.path.join(wheel, "pip"), "--version"], timeout_s=120)
    assert proc.returncode == 0 and proc.stdout.startswith("pip "), proc.stdout + proc.stderr


def test_pip_error_is_one_line():
    lines = ["Collecting cupy-cuda13x<15,>=14", "ERROR: Could not find a version that satisfies the requirement "
             "cupy-cuda13x<15,>=14 (from versions: none)", "ERROR: No matching distribution found for cupy-cuda13x"]
    assert gpu.pip_error(lines, 1) == "No matching distribution found for cupy-cuda13x"
    assert gpu.pip_error(["Traceback (most recent call last):", "  ...", "OSError: disk full", ""], 2) == \
        "OSError: disk full"
    assert gpu.pip_error([], 9) == "pip exited with code 9"


# --------------------------------------------------------------------------- the installer

def _fake_pip(tmp_path, body: str) -> list[str]:
    """A stand-in for pip: this Python running ``body`` with ``target`` = the --target folder."""
    script = tmp_path / "fake_pip.py"
    script.write_text("import os, sys, time\ntarget = sys.argv[sys.argv.index('--target') + 1]\n"
                      + textwrap.dedent(body), encoding="utf-8")
    return gpu.cupy_install_command(sys.executable, "STAGING", "cupy-cuda12x", numpy_version="1.26.4",
                                    pip=[sys.executable, str(script)])


def _with_target(command: list[str], staging) -> list[str]:
    return [str(staging) if part == "STAGING" else part for part in command]


FAKE_SUCCESS = """
print("Collecting cupy-cuda12x<14,>=13.3", flush=True)
print("  Downloading cupy_cuda12x-13.6.0-cp311-cp311-manylinux2014_x86_64.whl (113.0 MB)", flush=True)
os.makedirs(os.path.join(target, "cupy_cuda12x-13.6.0.dist-info"))
with open(os.path.join(target, "cupy_cuda12x-13.6.0.dist-info", "METADATA"), "w") as fh:
    fh.write("Metadata-Version: 2.1\\nName: cupy-cuda12x\\nVersion: 13.6.0\\n")
print("Successfully installed cupy-cuda12x-13.6.0 fastrlock-0.8.4", flush=True)
"""


def test_installer_success_replaces_folder(tmp_path):
    target = tmp_path / "site-packages"
    (target / "old_package").mkdir(parents=True)
    staging = tmp_path / "site-packages.partial"
    installer = gpu.Installer(_with_target(_fake_pip(tmp_path, FAKE_SUCCESS), staging), str(staging), str(target))
    installer.run()
    assert installer.state == "done", installer.message
    assert installer.message == "Successfully installed cupy-cuda12x-13.6.0 fastrlock-0.8.4"
    assert installer.progress.startswith("Successfully installed")
    assert sorted(os.listdir(target)) == ["cupy_cuda12x-13.6.0.dist-info"]      # the old folder is gone
    assert not staging.exists() and not (tmp_path / "site-packages.old").exists()


def test_installer_failure_keeps_old_folder(tmp_path):
    target = tmp_path / "site-packages"
    (target / "cupy").mkdir(parents=True)
    staging = tmp_path / "site-packages.partial"
    body = """
    os.makedirs(target)
    print("Collecting cupy-cuda13x<15,>=14")
    print("ERROR: No matching distribution found for cupy-cuda13x")
    sys.exit(1)
    """
    installer = gpu.Installer(_with_target(_fake_pip(tmp_path, body), staging), str(staging), str(target))
    installer.start()
    installer.join(60)
    assert installer.state == "error"
    assert installer.message == "No matching distribution found for cupy-cuda13x"
    assert os.listdir(target) == ["cupy"] and not staging.exists()


def test_installer_cancel_stops_pip(tmp_path):
    staging, target = tmp_path / "partial", tmp_path / "site-packages"
    body = """
    os.makedirs(target)
    print("Collecting cupy-cuda12x", flush=True)
    time.sleep(60)
    """
    installer = gpu.Installer(_with_target(_fake_pip(tmp_path, body), staging), str(staging), str(target))
    installer.start()
    for _ in range(500):
        if installer.progress.startswith("Collecting"):
            break
        import time
        time.sleep(0.01)
    installer.cancel()
    installer.join(30)
    assert not installer.thread.is_alive()
    assert installer.state == "cancelled" and "nothing changed" in installer.message
    assert not staging.exists() and not target.exists()


def test_installer_missing_program_is_an_error(tmp_path):
    installer = gpu.Installer([str(tmp_path / "no-python"), "-m", "pip"], str(tmp_path / "p"), str(tmp_path / "t"))
    installer.run()
    assert installer.state == "error" and "no-python" in installer.message


# --------------------------------------------------------------------------- folder, libraries, status

def _touch(root: Path, *names: str) -> None:
    for name in names:
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")


def test_cuda_library_files_linux_cuda12_and_13(tmp_path):
    cu12 = tmp_path / "cu12"
    _touch(cu12, "nvidia/cublas/lib/libcublas.so.12", "nvidia/cublas/lib/libcublasLt.so.12",
           "nvidia/cublas/lib/libnvblas.so.12", "nvidia/cuda_nvrtc/lib/libnvrtc.so.12",
           "nvidia/cuda_nvrtc/lib/libnvrtc.alt.so.12", "nvidia/cuda_nvrtc/lib/libnvrtc-builtins.so.12.9",
           "nvidia/cuda_nvrtc/lib/libnvrtc-builtins.alt.so.12.9", "nvidia/cufft/lib/libcufft.so.11",
           "nvidia/cufft/lib/libcufftw.so.11", "nvidia/nvjitlink/lib/libnvJitLink.so.12")
    names = [os.path.relpath(p, cu12) for p in gpu.cuda_library_files(str(cu12), "linux")]
    assert names == ["nvidia/nvjitlink/lib/libnvJitLink.so.12", "nvidia/cuda_nvrtc/lib/libnvrtc-builtins.so.12.9",
                     "nvidia/cuda_nvrtc/lib/libnvrtc.so.12", "nvidia/cublas/lib/libcublasLt.so.12",
                     "nvidia/cublas/lib/libcublas.so.12", "nvidia/cufft/lib/libcufft.so.11"]
    cu13 = tmp_path / "cu13"   # the layout measured on the GPU machine (cupy-cuda13x 14.2 with CUDA 13 wheels)
    _touch(cu13, *(f"nvidia/cu13/lib/{n}" for n in (
        "libnvJitLink.so.13", "libcufftw.so.12", "libnvrtc.so.13", "libnvblas.so.13", "libnvrtc-builtins.so.13.0",
        "libcublasLt.so.13", "libcufft.so.12", "libcublas.so.13", "libnvrtc.alt.so.13",
        "libnvrtc-builtins.alt.so.13.0")))
    assert [os.path.basename(p) for p in gpu.cuda_library_files(str(cu13), "linux")] == [
        "libnvJitLink.so.13", "libnvrtc-builtins.so.13.0", "libnvrtc.so.13", "libcublasLt.so.13",
        "libcublas.so.13", "libcufft.so.12"]
    assert gpu.cuda_library_files(str(tmp_path / "empty"), "linux") == []


def test_cuda_library_files_windows(tmp_path):
    _touch(tmp_path, "nvidia/cublas/bin/cublas64_12.dll", "nvidia/cublas/bin/cublasLt64_12.dll",
           "nvidia/cublas/bin/nvblas64_12.dll", "nvidia/cuda_nvrtc/bin/nvrtc64_120_0.dll",
           "nvidia/cuda_nvrtc/bin/nvrtc64_120_0.alt.dll", "nvidia/cuda_nvrtc/bin/nvrtc-builtins64_129.dll",
           "nvidia/cufft/bin/cufft64_11.dll", "nvidia/cufft/bin/cufftw64_11.dll",
           "nvidia/nvjitlink/bin/nvJitLink_120_0.dll")
    assert [os.path.basename(p) for p in gpu.cuda_library_files(str(tmp_path), "win32")] == [
        "nvJitLink_120_0.dll", "nvrtc-builtins64_129.dll", "nvrtc64_120_0.dll", "cublasLt64_12.dll",
        "cublas64_12.dll", "cufft64_11.dll"]


def test_load_cuda_libraries_reports_broken_files(tmp_path):
    _touch(tmp_path, "nvidia/cuda_nvrtc/lib/libnvrtc.so.12", "nvidia/cuda_nvrtc/bin/nvrtc64_120_0.dll")
    problems = gpu.load_cuda_libraries(str(tmp_path))      # empty files: not loadable, reported, no exception
    assert len(problems) == 1 and problems[0].startswith(("libnvrtc.so.12: ", "nvrtc64_120_0.dll: "))
    assert gpu.load_cuda_libraries(str(tmp_path / "none")) == []


def test_sys_path_only_for_existing_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "path", list(sys.path))
    missing = str(tmp_path / "missing")
    assert not gpu.add_to_sys_path(missing) and missing not in sys.path and not os.path.exists(missing)
    assert gpu.add_to_sys_path(str(tmp_path)) and sys.path[-1] == str(tmp_path)   # after Blender's own
    assert gpu.add_to_sys_path(str(tmp_path)) and sys.path.count(str(tmp_path)) == 1
    gpu.remove_from_sys_path(str(tmp_path))
    assert str(tmp_path) not in sys.path


def test_installed_cupy_reads_metadata_without_import(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "path", [*sys.path, str(tmp_path)])
    imported = "cupy" in sys.modules
    before = gpu.installed_cupy()
    dist = tmp_path / "cupy_cuda12x-13.6.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: cupy-cuda12x\nVersion: 13.6.0\n")
    found = gpu.installed_cupy()
    assert ("cupy-cuda12x", "13.6.0", str(tmp_path)) in [(n, v, os.path.normpath(f)) for n, v, f in found]
    assert len(found) == len(before) + 1
    assert ("cupy" in sys.modules) == imported                   # found without importing it


@pytest.mark.parametrize(("system", "machine", "ok"), [
    ("linux", "x86_64", True), ("linux", "aarch64", True), ("win32", "AMD64", True),
    ("win32", "ARM64", False), ("darwin", "arm64", False)])
def test_platform_problem(system, machine, ok):
    problem = gpu.platform_problem(system, machine)
    assert (problem is None) == ok
    if system == "darwin":
        assert "macOS" in problem


def test_status_lines():
    assert gpu.Status(cupy=[]).line() == (
        "CuPy is not installed in Blender's Python: GPU rendering needs it (Install CuPy for GPU rendering)", 'INFO')
    cupy = [("cupy-cuda12x", "13.6.0", "/x")]
    assert gpu.Status(cupy=cupy).line()[0] == "cupy-cuda12x 13.6.0 installed; GPU not checked yet (Check GPU)"
    ready = gpu.Status(cupy=cupy, device="GPU 0: NVIDIA GeForce RTX 4090 (CuPy 13.6.0)")
    assert ready.line() == ("Ready: GPU 0: NVIDIA GeForce RTX 4090 (CuPy 13.6.0)", 'CHECKMARK')
    broken = gpu.Status(cupy=cupy, problem="GPU: CuPy 13.6.0 found no usable CUDA device (CUDARuntimeError: "
                                           "cudaErrorInsufficientDriver)")
    assert broken.line()[1] == 'ERROR' and "cudaErrorInsufficientDriver" in broken.line()[0]
    two = gpu.Status(cupy=[*cupy, ("cupy-cuda13x", "14.2.0", "/y")])
    assert two.line()[0].startswith("Several CuPy packages installed (cupy-cuda12x 13.6.0, cupy-cuda13x 14.2.0)")
    assert gpu.Status(platform_problem="no CUDA on macOS", cupy=cupy).line() == ("no CUDA on macOS", 'ERROR')


# --------------------------------------------------------------------------- the warm-up after an install

def test_warmup_command_loads_the_cuda_libraries_then_runs_tofcores_warmup():
    command = gpu.warmup_command("/blender/python3.11", "gpu", ["/f/nvidia/cuda_nvrtc/lib/libnvrtc.so.12"])
    assert command[:3] == ["/blender/python3.11", "-c", gpu.WARMUP_PROGRAM]
    assert command[3:] == ["gpu", "/f/nvidia/cuda_nvrtc/lib/libnvrtc.so.12"]
    assert 'main(["warmup", "--device", sys.argv[1]])' in gpu.WARMUP_PROGRAM
    assert gpu.warmup_env()["PYTHONPATH"].split(os.pathsep) == [p for p in sys.path if p]


def _warmup_env() -> dict:
    """The real program, on the CPU with the NumPy tracer (about a second): tofcore from this checkout."""
    return dict(os.environ, PYTHONPATH=str(REPO_ROOT), TOFCORE_TRACER="numpy")


def test_the_warmup_program_runs_tofcores_warmup_and_reports_ready():
    warmup = gpu.Warmup(gpu.warmup_command(sys.executable, "cpu"), env=_warmup_env())
    assert warmup.line()[0].startswith("Warming up the GPU kernels in the background: 0 s…")
    warmup.start()
    warmup.join(120)
    assert warmup.state == "done", warmup.message
    assert warmup.message.startswith("numpy tracer on the CPU (TOFCORE_TRACER=numpy): ready in ")
    text, icon = warmup.line()
    assert text == f"GPU kernels ready in {warmup.seconds:.0f} s (compiled once, cached for later renders)"
    assert icon == 'CHECKMARK' and warmup.seconds > 0


def test_a_failed_warmup_is_one_line(tmp_path):
    broken = tmp_path / "libnvrtc.so.12"
    broken.write_bytes(b"not a library")
    warmup = gpu.Warmup(gpu.warmup_command(sys.executable, "gpu", [str(broken)]), env=_warmup_env())
    warmup.run()
    assert warmup.state == "error" and warmup.message.startswith("exit status 1: OSError: ")
    text, icon = warmup.line()
    assert text.startswith("GPU kernel warm-up failed: exit status 1: OSError: ") and icon == 'ERROR'
    assert text.endswith("; the first GPU render compiles them")
    missing = gpu.Warmup([str(tmp_path / "no-python"), "-c", "pass"], env=_warmup_env())
    missing.run()
    assert missing.state == "error" and "could not be started" in missing.message


def test_start_warmup_starts_one_at_a_time(tmp_path, monkeypatch):
    started = []
    monkeypatch.setattr(gpu, "_warmup", None)
    monkeypatch.setattr(gpu.Warmup, "start", lambda self: started.append(self.command))
    first = gpu.start_warmup(str(tmp_path), python="py")
    assert gpu.start_warmup(str(tmp_path), python="py") is first and gpu.warmup() is first   # it runs
    assert started == [["py", "-c", gpu.WARMUP_PROGRAM, "gpu"]]                             # no libraries there
    first.state = "error"
    assert gpu.start_warmup(str(tmp_path), python="py") is not first and len(started) == 2  # a new one
