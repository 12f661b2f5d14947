"""CuPy in Blender's Python: the folder it is installed into, the pip command, the CUDA libraries, the status.

tofcore renders on an NVIDIA GPU through CuPy (``device="gpu"`` or ``"auto"``, :mod:`tofcore.backend`).
Blender ships NumPy but not CuPy, and the extension zips stay small (CuPy and the CUDA libraries are
about 1 GB), so the user installs CuPy on request: the preferences' button (:func:`cupy_install_command`
run by an :class:`Installer`), or the same command by hand (docs/blender.md, "GPU in Blender").

===================  =====================================================================================
what                 how
===================  =====================================================================================
where it goes        :func:`site_packages_dir`: the extension's own user folder
                     (``<user config>/extensions/.user/<repo>/tof_camera/site-packages``, one per Blender
                     version), never Blender's bundled site-packages (read-only in many installs, shared by
                     every add-on). :func:`add_to_sys_path` appends it at registration: Blender's own
                     packages (NumPy) come first.
which Python         ``sys.executable``: Blender's own Python (``<blender>/<version>/python/bin/python3.x``).
                     Where pip is missing there, the pip wheel that ``ensurepip`` bundles runs directly
                     (:func:`pip_command`), so nothing is written into Blender's Python to get pip.
which CuPy           CuPy 14 requires NumPy ≥ 2 (Blender 5.1+, Python 3.13); Blender 4.2–5.0 ship NumPy 1.26,
                     for which CuPy 13 (≥ 13.3) is the newest (:func:`cupy_requirements`).
which CUDA           ``cupy-cuda12x``: any NVIDIA driver ≥ 525 (CUDA 12 minor-version compatibility), GPUs
                     from Maxwell on; the default. ``cupy-cuda13x``: driver ≥ 580 and a Turing or newer GPU
                     (CUDA 13 dropped Maxwell, Pascal and Volta). Never both: they are one ``cupy`` module.
dependencies         ``pip install --target`` resolves as if nothing were installed, so CuPy's requirement
                     ``numpy`` would put a second NumPy into the folder (CuPy 14 asks for NumPy ≥ 2 even on
                     Blender 5.0). The command therefore uses ``--no-deps`` and names CuPy's other
                     dependencies itself: ``fastrlock`` (CuPy 13) or ``cuda-pathfinder`` (CuPy 14).
CUDA libraries       CuPy's wheel has the CUDA runtime built in but loads NVRTC (it compiles every kernel),
                     cuBLAS (matrix products) and cuFFT (lens scattering) from a CUDA Toolkit or NVIDIA's
                     pip wheels. Most Blender users have only the driver, so the command installs the
                     wheels (``nvidia-cuda-nvrtc``, ``nvidia-cublas``, ``nvidia-cufft``, ``nvidia-nvjitlink``).
loading them         CuPy 13 looks for these libraries on the system's library path, CuPy 14 (through
                     cuda-pathfinder) also in ``site.getsitepackages()``; the add-on's folder is neither.
                     :func:`load_cuda_libraries` loads them by full path before the first GPU render
                     (:func:`activate`); CuPy's later ``dlopen``/``LoadLibrary`` by name then finds them loaded.
===================  =====================================================================================

After a successful install, :func:`start_warmup` has the GPU's kernels compiled once by a child process of
Blender's Python (:class:`Warmup`: ``tofcore warmup --device gpu``, the CUDA libraries loaded first as
:func:`load_cuda_libraries` does here), so that the first GPU render loads them from CuPy's and numba's caches
instead of compiling; the preferences show its state.

The module imports ``bpy`` only inside :func:`site_packages_dir`, and CuPy only through
:func:`tofcore.backend.select_device` in :func:`check`, never at registration. pip runs in a subprocess
(``fork`` + ``exec``: the child runs no Python of this process, which matters because a process that
imported bpy hangs in a plain ``fork``) with ``close_fds``; so does the warm-up.
"""

from __future__ import annotations

import atexit
import ctypes
import glob
import importlib
import importlib.metadata
import os
import platform
import re
import shutil
import subprocess
import sys
import threading
from dataclasses import dataclass

#: Name of the add-on's CuPy folder inside its user folder.
SITE_PACKAGES = "site-packages"


@dataclass(frozen=True)
class CudaLine:
    """One choice of CuPy wheel: its pip name, the UI text, and the NVIDIA library wheels it needs."""

    package: str
    label: str
    description: str
    libraries: tuple[str, ...]


#: The CuPy packages the preferences offer (``cupy_package``), CUDA 12 first (the default).
CUDA_LINES = (
    CudaLine("cupy-cuda12x", "CUDA 12 (driver ≥ 525)",
             "cupy-cuda12x with NVIDIA's CUDA 12 libraries: any NVIDIA driver from 525 on and GPUs from "
             "Maxwell (GeForce 900) on; the safe choice",
             ("nvidia-cuda-nvrtc-cu12==12.*", "nvidia-cublas-cu12==12.*", "nvidia-cufft-cu12==11.*",
              "nvidia-nvjitlink-cu12==12.*")),
    CudaLine("cupy-cuda13x", "CUDA 13 (driver ≥ 580)",
             "cupy-cuda13x with NVIDIA's CUDA 13 libraries: needs driver 580 or newer and a Turing "
             "(GeForce 16/RTX 20) or newer GPU; CUDA 13 dropped Maxwell, Pascal and Volta",
             ("nvidia-cuda-nvrtc==13.*", "nvidia-cublas==13.*", "nvidia-cufft==12.*", "nvidia-nvjitlink==13.*")),
)
DEFAULT_PACKAGE = CUDA_LINES[0].package

#: CUDA libraries loaded by :func:`load_cuda_libraries`, dependencies first (file-name stems). NVRTC loads its
#: builtins by name at its first compile, which would find a system CUDA Toolkit's copy or none: loaded here too.
CUDA_LIBRARIES = ("nvJitLink", "nvrtc-builtins", "nvrtc", "cublasLt", "cublas", "cufft")


class InstallError(RuntimeError):
    """CuPy cannot be installed; the message is one line naming the cause."""


def cuda_line(package: str) -> CudaLine:
    for line in CUDA_LINES:
        if line.package == package:
            return line
    raise InstallError(f"cupy_package must be one of {[line.package for line in CUDA_LINES]}, got {package!r}")


# --------------------------------------------------------------------------- the pip command (pure)

def cupy_requirements(package: str, numpy_version: str) -> list[str]:
    """pip requirements for ``package`` (``"cupy-cuda12x"`` or ``"cupy-cuda13x"``) beside NumPy ``numpy_version``.

    CuPy 14 requires NumPy ≥ 2 and ``cuda-pathfinder``; CuPy 13 (≥ 13.3: NumPy 1.26 and Python 3.11/3.13
    wheels) supports NumPy 1.22–2.x and requires ``fastrlock``. Both major versions are capped, since
    their dependencies are listed here by hand (``--no-deps``).
    """
    line = cuda_line(package)
    major = re.match(r"\d+", numpy_version)
    if major is not None and int(major.group()) >= 2:
        cupy = [f"{package}>=14,<15", "cuda-pathfinder>=1.3.4,<2"]
    else:
        cupy = [f"{package}>=13.3,<14", "fastrlock>=0.5"]
    return cupy + list(line.libraries)


def cupy_install_command(python: str, target: str, package: str, *, numpy_version: str | None = None,
                         pip: list[str] | None = None) -> list[str]:
    """The command line that installs CuPy ``package`` and its CUDA libraries into folder ``target``.

    Parameters
    ----------
    python : Blender's Python (``sys.executable`` inside Blender).
    target : the folder (``pip install --target``); replaced as a whole when it exists (``--upgrade``).
    package : ``"cupy-cuda12x"`` or ``"cupy-cuda13x"``.
    numpy_version : the NumPy of that Python (default: this process's, which is the same Python in Blender);
        it picks CuPy 13 or 14 (:func:`cupy_requirements`).
    pip : how to run pip (default ``[python, "-m", "pip"]``; :func:`pip_command`).

    Binary wheels only (no compiler needed), no dependencies resolved by pip (Blender's NumPy stays the
    only NumPy), no prompts, no progress bars (the output is read line by line).
    """
    if numpy_version is None:
        import numpy
        numpy_version = numpy.__version__
    pip = list(pip) if pip else [python, "-m", "pip"]
    return [*pip, "install", "--target", target, "--upgrade", "--no-deps", "--only-binary=:all:",
            "--no-input", "--disable-pip-version-check", "--progress-bar", "off", "--no-warn-script-location",
            *cupy_requirements(package, numpy_version)]


def bundled_pip_wheel() -> str | None:
    """The pip wheel inside this Python's ``ensurepip`` (runs as ``python <wheel>/pip``), or None."""
    try:
        import ensurepip
    except ImportError:
        return None
    wheels = sorted(glob.glob(os.path.join(os.path.dirname(ensurepip.__file__), "_bundled", "pip-*.whl")))
    return wheels[-1] if wheels else None


def pip_command(python: str, *, timeout_s: float = 120.0) -> list[str]:
    """How to run pip with ``python``: ``[python, "-m", "pip"]`` when pip is installed there, else
    ``[python, "<ensurepip's bundled wheel>/pip"]`` (pip runs from its wheel; nothing is installed).

    Raises :class:`InstallError` when neither works (Debian's Blender 4.3: its Python 3.13 has neither); the
    caller says how to install by hand.
    """
    probe = run_quiet([python, "-m", "pip", "--version"], timeout_s=timeout_s)
    if probe.returncode == 0:
        return [python, "-m", "pip"]
    wheel = bundled_pip_wheel()
    if wheel is not None:
        command = [python, os.path.join(wheel, "pip")]
        if run_quiet([*command, "--version"], timeout_s=timeout_s).returncode == 0:
            return command
    raise InstallError(f"pip is not available in Blender's Python ({python}) and ensurepip has no pip wheel")


def pip_env() -> dict[str, str]:
    """The environment of pip: this one, without user site-packages, prompts or version checks."""
    env = dict(os.environ)
    env.update(PYTHONNOUSERSITE="1", PIP_NO_INPUT="1", PIP_DISABLE_PIP_VERSION_CHECK="1",
               PIP_REQUIRE_VIRTUALENV="0")
    return env


def _popen_options() -> dict:
    # No console window flashing up on Windows; no inherited file descriptors (Blender's files, sockets).
    return {"close_fds": True, "creationflags": getattr(subprocess, "CREATE_NO_WINDOW", 0), "env": pip_env()}


def run_quiet(command: list[str], *, timeout_s: float) -> subprocess.CompletedProcess:
    """Run ``command`` (fork + exec, no shell), output captured; a missing program or a timeout is a
    non-zero return code, not an exception."""
    try:
        return subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False,
                              stdin=subprocess.DEVNULL, **_popen_options())
    except (OSError, subprocess.TimeoutExpired) as err:
        return subprocess.CompletedProcess(command, 127, "", f"ERROR: {err}")


def pip_error(lines: list[str], returncode: int) -> str:
    """One line naming why pip failed: its last ``ERROR:`` line, else its last line, else the exit code."""
    errors = [ln.strip()[len("ERROR:"):].strip() for ln in lines if ln.strip().startswith("ERROR:")]
    errors = [e for e in errors if e]
    if errors:
        return errors[-1]
    text = [ln.strip() for ln in lines if ln.strip()]
    return text[-1] if text else f"pip exited with code {returncode}"


def replace_folder(new: str, target: str) -> None:
    """Make folder ``new`` the folder ``target``; the old ``target`` is removed.

    Renames, so ``target`` is never half written. Raises OSError when the old folder cannot be moved
    (Windows: CuPy from it is loaded in this Blender session).
    """
    old = target + ".old"
    if os.path.exists(old):
        shutil.rmtree(old, ignore_errors=True)
    if os.path.exists(target):
        os.replace(target, old)
    os.replace(new, target)
    shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- the installer (a worker, no bpy)

class Installer:
    """Runs the pip command into a staging folder, then swaps it in as ``target``.

    ``run()`` works in the calling thread (background mode), ``start()`` in a daemon thread (the UI
    polls ``state``, ``progress`` and ``message``). ``state``: ``"running"``, ``"done"``, ``"error"``,
    ``"cancelled"``; ``message``: one line (the error, or what was installed).
    """

    def __init__(self, command: list[str], staging: str, target: str, what: str = "CuPy") -> None:
        self.command = list(command)
        self.what = what  # the package's name in messages
        self.staging, self.target = staging, target
        self.lines: list[str] = []
        self.state = "running"
        self.message = ""
        self.thread: threading.Thread | None = None
        self._proc: subprocess.Popen | None = None
        self._cancel = threading.Event()

    @property
    def progress(self) -> str:
        """pip's latest step: "Collecting …", "Downloading … (581.2 MB)", "Installing collected packages …"."""
        for line in reversed(self.lines):
            text = line.strip()
            if text.startswith(("Collecting", "Downloading", "Installing", "Using cached", "Successfully")):
                return text
        return "starting pip"

    def cancel(self) -> None:
        self._cancel.set()
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()

    def run(self) -> None:
        try:
            self._run()
        except OSError as err:
            self.state, self.message = "error", f"{type(err).__name__}: {err}"
        finally:
            if self.state != "done":
                shutil.rmtree(self.staging, ignore_errors=True)

    def _run(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        os.makedirs(os.path.dirname(self.staging) or ".", exist_ok=True)
        self._proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                      stdin=subprocess.DEVNULL, bufsize=1, errors="replace", **_popen_options())
        for line in self._proc.stdout:
            self.lines.append(line.rstrip())
            del self.lines[:-200]
        returncode = self._proc.wait()
        if self._cancel.is_set():
            self.state, self.message = "cancelled", f"{self.what} installation cancelled; nothing changed"
            return
        if returncode != 0:
            self.state, self.message = "error", pip_error(self.lines, returncode)
            return
        try:
            replace_folder(self.staging, self.target)
        except OSError as err:
            self.state = "error"
            self.message = (f"cannot replace {self.target} ({err.strerror or err}); the {self.what} in it is in use: "
                            f"restart Blender, then install again")
            return
        installed = next((ln.strip() for ln in reversed(self.lines) if ln.startswith("Successfully installed")),
                         f"Successfully installed {self.what}")
        self.state, self.message = "done", installed

    def start(self) -> None:
        self.thread = threading.Thread(target=self.run, name=f"tof-install-{self.what.lower()}", daemon=True)
        self.thread.start()

    def join(self, timeout: float | None = None) -> None:
        if self.thread is not None:
            self.thread.join(timeout)


# --------------------------------------------------------------------------- the warm-up (a child process, no bpy)

#: The warm-up child's program (``python -c``): the add-on's CUDA libraries loaded by full path, as
#: :func:`load_cuda_libraries` loads them in Blender (neither CuPy 13 nor Windows' DLL search would find them by
#: name), then ``tofcore warmup --device <argv[1]>`` (:func:`tofcore.cli.cmd_warmup`).
WARMUP_PROGRAM = """
import ctypes, os, sys
mode = getattr(os, "RTLD_GLOBAL", 0) | getattr(os, "RTLD_NOW", 0)
for path in sys.argv[2:]:
    if hasattr(os, "add_dll_directory"):
        os.add_dll_directory(os.path.dirname(path))
    ctypes.CDLL(path, mode=mode)
from tofcore.cli import main
sys.exit(main(["warmup", "--device", sys.argv[1]]))
"""


def warmup_command(python: str, device: str = "gpu", libraries: list[str] | tuple[str, ...] = ()) -> list[str]:
    """The command line of the warm-up child: Blender's Python running ``tofcore warmup --device DEVICE`` after
    loading ``libraries`` (:func:`cuda_library_files` of the add-on's CuPy folder)."""
    return [python, "-c", WARMUP_PROGRAM, device, *libraries]


def warmup_env() -> dict[str, str]:
    """The warm-up child's environment: this one with ``PYTHONPATH`` = this process's ``sys.path`` (Blender's,
    the extension's and the add-on's CuPy and numba folders), so the child imports the same tofcore, CuPy and
    numba, as ``tofcore.compiled.child_compile`` does for the CPU's."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
    return env


class Warmup:
    """``tofcore warmup`` in a child process (started after an install), watched by a daemon thread: the GPU's
    kernels (CuPy's, numba-cuda's where installed) compiled and cached once, so that the first GPU render loads
    them instead of compiling.

    Never blocks: :meth:`start` returns at once; the preferences draw :meth:`line`. ``state``: ``"running"``,
    ``"done"``, ``"error"``; ``seconds``: how long it ran (so far); ``message``: its last line (what
    ``tofcore warmup`` said, or why it failed).
    """

    def __init__(self, command: list[str], env: dict[str, str] | None = None, what: str = "GPU") -> None:
        self.command, self.env, self.what = list(command), env, what
        self.state = "running"
        self.message = ""
        self.lines: list[str] = []
        self.thread: threading.Thread | None = None
        self._proc: subprocess.Popen | None = None
        self._started = self._ended = None

    @property
    def seconds(self) -> float:
        import time

        if self._started is None:
            return 0.0
        return (self._ended if self._ended is not None else time.perf_counter()) - self._started

    def run(self) -> None:
        import time

        self._started = time.perf_counter()
        try:
            options = dict(_popen_options(), env=self.env if self.env is not None else warmup_env())
            self._proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                          stdin=subprocess.DEVNULL, bufsize=1, errors="replace", **options)
            for line in self._proc.stdout:
                if line.strip():
                    self.lines.append(line.strip())
                    del self.lines[:-50]
            returncode = self._proc.wait()
        except OSError as err:
            self.state, self.message = "error", f"{self.command[0]} could not be started ({err.strerror or err})"
            return
        finally:
            self._ended = time.perf_counter()
        if returncode == 0:
            self.state, self.message = "done", self.lines[-1] if self.lines else ""
        else:
            self.state = "error"
            self.message = f"exit status {returncode}" + (f": {self.lines[-1]}" if self.lines else "")

    def start(self) -> None:
        self.thread = threading.Thread(target=self.run, name=f"tof-warmup-{self.what.lower()}", daemon=True)
        self.thread.start()

    def join(self, timeout: float | None = None) -> None:
        if self.thread is not None:
            self.thread.join(timeout)

    def stop(self) -> None:
        """Stop the child (Blender quits: a stopped compile leaves nothing half-written, numba and CuPy write their
        cache files by atomic renames)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()

    def line(self) -> tuple[str, str]:
        """(text, icon) for the preferences: warming…, ready in N s, or failed: one line."""
        if self.state == "running":
            return (f"Warming up the {self.what} kernels in the background: {self.seconds:.0f} s… (compiled once; "
                    f"a render meanwhile compiles what it needs itself)", 'SORTTIME')
        if self.state == "done":
            return f"{self.what} kernels ready in {self.seconds:.0f} s (compiled once, cached for later renders)", \
                'CHECKMARK'
        return (f"{self.what} kernel warm-up failed: {self.message}; the first {self.what} render compiles them",
                'ERROR')


_warmup: Warmup | None = None


def start_warmup(folder: str, python: str | None = None) -> Warmup:
    """Start warming up the GPU kernels in the background (after CuPy was installed into ``folder``), unless a
    warm-up runs already; the :class:`Warmup` (also :func:`warmup`)."""
    global _warmup
    if _warmup is None or _warmup.state != "running":
        _warmup = Warmup(warmup_command(python or sys.executable, "gpu", cuda_library_files(folder)))
        _warmup.start()
    return _warmup


def warmup() -> Warmup | None:
    """The GPU warm-up of this Blender session (:func:`start_warmup`), or None."""
    return _warmup


def _stop_warmup() -> None:
    if _warmup is not None:
        _warmup.stop()


atexit.register(_stop_warmup)


# --------------------------------------------------------------------------- the folder, sys.path, libraries

def site_packages_dir(package: str | None = None) -> str:
    """The add-on's CuPy folder (not created): the extension's user folder, or for a plain add-on folder
    (not installed as an extension, e.g. the tests) ``<user datafiles>/tof_camera/site-packages``."""
    import bpy

    package = package or __package__
    try:
        return bpy.utils.extension_path_user(package, path=SITE_PACKAGES, create=False)
    except ValueError:  # "package" does not name an extension
        return os.path.join(bpy.utils.user_resource('DATAFILES', path="tof_camera"), SITE_PACKAGES)


def add_to_sys_path(folder: str) -> bool:
    """Append ``folder`` to ``sys.path`` if it exists (after Blender's own packages); True if it is there."""
    if not folder or not os.path.isdir(folder):
        return False
    if folder not in sys.path:
        sys.path.append(folder)
        importlib.invalidate_caches()
    return True


def remove_from_sys_path(folder: str) -> None:
    while folder and folder in sys.path:
        sys.path.remove(folder)


#: Libraries loaded by :func:`load_cuda_libraries` (path → handle; kept so they stay loaded) and the
#: Windows DLL folders added (their handles must stay alive too).
_loaded_libraries: dict[str, object] = {}
_dll_directories: dict[str, object] = {}


def cuda_library_files(folder: str, system: str | None = None) -> list[str]:
    """The NVIDIA wheel libraries in ``folder`` to load, in :data:`CUDA_LIBRARIES` order.

    Linux: ``nvidia/*/lib/lib<name>.so.<major>`` (``.so.<major>.<minor>`` for NVRTC's builtins; CUDA 12
    wheels: one folder per library, CUDA 13: ``nvidia/cu13/lib``); the ``.alt`` variants are skipped.
    Windows: ``nvidia/**/<name>64_*.dll`` / ``<name>_*.dll``.
    """
    system = system or sys.platform
    found = []
    if system == "win32":
        dlls = sorted(glob.glob(os.path.join(folder, "nvidia", "**", "*.dll"), recursive=True))
        for name in CUDA_LIBRARIES:
            pattern = re.compile(rf"{re.escape(name)}(64)?_\d+(_\d+)?\.dll$", re.I)
            found += [p for p in dlls if pattern.match(os.path.basename(p))][:1]
    else:
        libs = sorted(glob.glob(os.path.join(folder, "nvidia", "*", "lib", "lib*.so.*")))
        for name in CUDA_LIBRARIES:
            pattern = re.compile(rf"lib{re.escape(name)}\.so\.\d+(\.\d+)?$")
            found += [p for p in libs if pattern.match(os.path.basename(p))][:1]
    return found


def load_cuda_libraries(folder: str) -> list[str]:
    """Load the CUDA libraries of ``folder`` into this process, once; returns one line per library that
    failed to load (none: all loaded, or none installed there, e.g. a system CUDA Toolkit is used)."""
    problems = []
    if sys.platform == "win32":
        for path in cuda_library_files(folder):
            directory = os.path.dirname(path)
            if directory not in _dll_directories:
                try:
                    _dll_directories[directory] = os.add_dll_directory(directory)
                except OSError as err:
                    problems.append(f"{directory}: {err}")
    mode = getattr(os, "RTLD_GLOBAL", 0) | getattr(os, "RTLD_NOW", 0)
    for path in cuda_library_files(folder):
        if path in _loaded_libraries:
            continue
        try:
            _loaded_libraries[path] = ctypes.CDLL(path, mode=mode)
        except OSError as err:
            problems.append(f"{os.path.basename(path)}: {err}")
    return problems


# --------------------------------------------------------------------------- status

def platform_problem(system: str | None = None, machine: str | None = None) -> str | None:
    """Why CuPy cannot run on this computer (None: it has CuPy wheels: Linux x86-64/ARM64, Windows x86-64)."""
    system = system or sys.platform
    machine = (machine or platform.machine()).lower()
    if system == "darwin":
        return "GPU rendering needs an NVIDIA GPU with CUDA, which macOS does not have: render on the CPU"
    if system.startswith("linux") and machine in ("x86_64", "amd64", "aarch64", "arm64"):
        return None
    if system == "win32" and machine in ("amd64", "x86_64"):
        return None
    return f"CuPy has no wheels for {system} on {machine}: render on the CPU"


def installed_cupy() -> list[tuple[str, str, str]]:
    """CuPy distributions importable now: ``(name, version, folder)`` each, from package metadata (CuPy
    itself is not imported). Two or more means two ``cupy`` modules shadowing each other."""
    found, seen = [], set()
    for dist in importlib.metadata.distributions():
        name = (dist.metadata.get("Name") or "").lower()
        if not (name == "cupy" or name.startswith("cupy-cuda") or name.startswith("cupy-rocm")):
            continue
        location = str(dist.locate_file(""))
        if (name, location) in seen:
            continue
        seen.add((name, location))
        found.append((name, dist.version, location))
    return found


@dataclass
class Status:
    """What the preferences show: the CuPy installed and, once checked or rendered with, the GPU."""

    platform_problem: str | None = None
    cupy: list | None = None             # installed_cupy()
    device: str | None = None            # tofcore's device description after a GPU check or render
    problem: str | None = None           # why the last check found no usable GPU (one line)
    library_problems: tuple[str, ...] = ()

    def line(self) -> tuple[str, str]:
        """(text, icon) of the status line."""
        if self.platform_problem:
            return self.platform_problem, 'ERROR'
        if not self.cupy:
            return ("CuPy is not installed in Blender's Python: GPU rendering needs it "
                    "(Install CuPy for GPU rendering)", 'INFO')
        names = ", ".join(f"{name} {version}" for name, version, _ in self.cupy)
        if len(self.cupy) > 1:
            return f"Several CuPy packages installed ({names}): remove all but one", 'ERROR'
        if self.device:
            return f"Ready: {self.device}", 'CHECKMARK'
        if self.problem:
            return f"{names} installed, but the GPU cannot run: {self.problem}", 'ERROR'
        return f"{names} installed; GPU not checked yet (Check GPU)", 'INFO'


_status: Status | None = None


def status(refresh: bool = False) -> Status:
    """The cached :class:`Status`; computed on first use (cheap: package metadata, no CuPy import).
    ``refresh`` starts over (after an install or for a new check)."""
    global _status
    if _status is None or refresh:
        _status = Status(platform_problem=platform_problem(), cupy=installed_cupy())
    return _status


def activate(folder: str) -> list[str]:
    """Make the CuPy of ``folder`` usable: on ``sys.path``, its CUDA libraries loaded. Cheap after the first
    call. Returns the library problems (also kept in the status)."""
    add_to_sys_path(folder)
    problems = load_cuda_libraries(folder) if os.path.isdir(folder) else []
    if problems:
        status().library_problems = tuple(problems)
    return problems


def check(folder: str) -> Status:
    """Import CuPy and run a kernel (:func:`tofcore.backend.select_device`); the status says which GPU or why
    none. Takes a second or two the first time (CUDA start-up, NVRTC)."""
    from tofcore import backend

    problems = activate(folder)
    result = status(refresh=True)
    result.library_problems = tuple(problems)
    if result.platform_problem:
        result.problem = result.platform_problem
        return result
    try:
        result.device = backend.select_device("gpu").description
    except backend.GpuUnavailable as err:
        result.problem = str(err)
        if problems:
            result.problem += f" (CUDA libraries: {problems[0]})"
    return result


def note_device(device: dict | None) -> None:
    """Update the status from a rendered frame's ``stats["device"]`` (a GPU render proves the GPU works)."""
    if not device:
        return
    current = status()
    if device.get("name") == "gpu":
        current.device, current.problem = device.get("description"), None
    elif device.get("fallback_reason"):
        current.device, current.problem = None, device["fallback_reason"]


def fallback_warning(reason: str) -> str:
    """The warning of an ``"auto"`` render that ran on the CPU, with the Blender way to get CuPy when missing
    (from the cached :func:`status`: the panel draws this on every redraw)."""
    if not status().cupy:
        return ("Rendered on the CPU: CuPy is not installed in Blender's Python (Preferences > Add-ons > "
                "ToF Camera Simulator > Install CuPy for GPU rendering)")
    return f"Rendered on the CPU: {reason}"
