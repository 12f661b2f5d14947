"""Build hook: ship the top-level ``presets/`` inside the wheel as ``tofcore/_presets``.

``presets/`` stays the single source in the repository; installed copies of
tofcore (a wheel, the Blender extension) find the same files next to the package.
All other metadata is in pyproject.toml.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithPresets(build_py):
    def run(self):
        super().run()
        target = Path(self.build_lib) / "tofcore" / "_presets"
        target.mkdir(parents=True, exist_ok=True)
        for preset in sorted(Path(__file__).parent.joinpath("presets").glob("*.toml")):
            shutil.copy2(preset, target / preset.name)


setup(cmdclass={"build_py": BuildWithPresets})
