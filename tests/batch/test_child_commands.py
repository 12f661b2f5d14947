"""The child processes batch starts for .blend files (``python -m <package>.blend inspect|export``) name a
module of the package they run from: ``batch`` in a checkout, ``tofcore_batch`` when installed
(tests/test_install.py runs the same check in an installed copy)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

#: Run in a fresh interpreter: records the commands instead of running them; prints one module name a line.
CHILD_COMMANDS = r"""
import importlib, importlib.util, subprocess, sys, threading
package = sys.argv[1]
if sys.argv[2:] == ["--from-checkout"]:    # ./batch imported under the installed name, as the wheel maps it
    spec = importlib.util.spec_from_file_location(package, "batch/__init__.py", submodule_search_locations=["batch"])
    sys.modules[package] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sys.modules[package])
jobs, worker = (importlib.import_module(f"{package}.{name}") for name in ("jobs", "worker"))
commands = []
def run(cmd, **kwargs):
    commands.append(cmd)
    return subprocess.CompletedProcess(cmd, 1, "", "stopped by the test")
subprocess.run = run
try:
    jobs.inspect_blend_subprocess("scene.blend")
except Exception:
    pass
def export():                      # off the main thread: the child-process path
    try:
        worker._export_blend("scene.blend", camera="Cam", frame=1)
    except Exception:
        pass
thread = threading.Thread(target=export)
thread.start()
thread.join()
assert len(commands) == 2, commands
for cmd in commands:
    assert cmd[:2] == [sys.executable, "-m"], cmd
    assert importlib.util.find_spec(cmd[2]) is not None, f"no module {cmd[2]!r}"
    print(cmd[2], cmd[3])
"""


@pytest.mark.parametrize("package", ["batch", "tofcore_batch"])
def test_blend_child_processes_run_a_module_of_this_package(package):
    flags = ["--from-checkout"] if package != "batch" else []
    proc = subprocess.run([sys.executable, "-c", CHILD_COMMANDS, package, *flags], cwd=REPO, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [f"{package}.blend inspect", f"{package}.blend export"]
