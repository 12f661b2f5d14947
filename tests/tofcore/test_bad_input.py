"""Bad input to ``tofcore render`` / ``tofcore presets`` (issue 12, classes 1–3): one line, exit code 2.

Every case runs the command line (``tofcore.cli.main(argv)`` in this process, and a few through
``python -m tofcore`` in a child process) and checks what the README promises: exit code 2, exactly
one error line on stderr (argparse's usage lines aside) naming the file, key or flag and the bad
value, no traceback, and no output folder.

1. malformed scene files (.npz), zip bombs refused before they are decompressed;
2. resource limits (:mod:`tofcore.limits`) checked before anything is allocated;
3. flags checked before rendering, physics values that would overflow the radiometric chain.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

import tofcore
from tofcore.output import writers
from tofcore.cli import main
from tofcore.sensor.presets import PRESETS_DIR

REPO = Path(__file__).resolve().parents[2]
KINECT = (PRESETS_DIR / "kinect_v2.toml").read_text()


# --------------------------------------------------------------------------- helpers

def run(argv: list[str], capsys) -> tuple[int, str]:
    """``tofcore ARGV`` in this process: (exit code, stderr)."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse errors
        code = exc.code
    return code, capsys.readouterr().err


def run_subprocess(*argv: str, env: dict | None = None) -> tuple[int, str]:
    """``python -m tofcore ARGV`` in a child process: (exit code, stderr)."""
    full_env = dict(os.environ, PYTHONPATH=str(REPO), **(env or {}))
    proc = subprocess.run([sys.executable, "-m", "tofcore", *argv], cwd=REPO, env=full_env, capture_output=True,
                          text=True, timeout=120)
    return proc.returncode, proc.stderr


def error_line(code: int, stderr: str) -> str:
    """The one error line, after checking exit code 2, no traceback and nothing else on stderr."""
    assert code == 2, stderr
    assert "Traceback" not in stderr, stderr
    # argparse prints its usage (possibly wrapped onto indented lines) before the error line.
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith(("usage:", " "))]
    assert len(lines) == 1, stderr
    return lines[0]


def assert_refused(code: int, stderr: str, *needles: str, out: Path | None = None) -> str:
    line = error_line(code, stderr)
    for needle in needles:
        assert needle in line, (needle, line)
    if out is not None:
        assert not out.exists(), sorted(out.iterdir())
    return line


def render_args(tmp_path: Path, *extra: str, scene: str = "plane", preset: str | None = None) -> list[str]:
    """A tiny render (scene ``plane``, a 16 x 12 Kinect v2, 1 spp) unless ``extra`` says otherwise."""
    return ["render", "--scene", scene, "--preset", preset or str(tiny_preset(tmp_path)), "--out",
            str(tmp_path / "out"), "--spp", "1", "--max-depth", "1", "--formats", "json", "--quiet", *extra]


def tiny_preset(folder: Path, **replace: str) -> Path:
    """The Kinect v2 preset at 16 x 12 px (no distortion), with ``key = value`` lines replaced."""
    text = KINECT
    lines = {"width": "16", "height": "12", "fx": "11.4", "fy": "11.4", "cx": "7.5", "cy": "5.5", "k1": "0.0",
             "k2": "0.0", "k3": "0.0", **replace}
    out = []
    for line in text.splitlines():
        key = line.split("=")[0].strip()
        out.append(f"{key} = {lines.pop(key)}" if key in lines and "=" in line else line)
    assert not lines, f"keys not in the preset: {lines}"
    path = folder / f"tiny_{abs(hash(tuple(sorted(replace.items()))))}.toml"
    path.write_text("\n".join(out) + "\n")
    return path


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def good_arrays(textured: bool = False) -> dict[str, np.ndarray]:
    """The arrays of a valid scene file (the demo plane; with a roughness texture if asked)."""
    scene = tofcore.demo_scene("plane")
    if textured:
        material = tofcore.Material(name="tex", roughness_texture=tofcore.Texture(np.full((2, 2), 0.3), name="r.png"))
        uvs = np.zeros((len(scene.vertices), 2), np.float32)
        scene = tofcore.Scene.from_arrays(scene.vertices, scene.triangles, None, [material], uvs=uvs, name="plane")
    with tempfile.TemporaryDirectory() as folder:
        with np.load(scene.save(Path(folder) / "good.npz")) as data:
            return {key: data[key] for key in data.files}


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, value in arrays.items():
            archive.writestr(f"{key}.npy", _npy(value))
    return path


def _header(**change) -> np.ndarray:
    header = {"name": "plane", "object_names": [], "materials": [{"name": "default"}], "dropped_triangles": 0,
              "metadata": {}}
    header.update(change)
    return np.array(json.dumps({k: v for k, v in header.items() if v is not None}))


# --------------------------------------------------------------------------- class 1: scene files

def _without(arrays: dict, key: str) -> dict:
    return {k: v for k, v in arrays.items() if k != key}


BAD_SCENES = {
    # name: (arrays → arrays, text the error names)
    "header_not_json": (lambda a: dict(a, header=np.array("{not json")), "header must be a JSON object"),
    "header_a_list": (lambda a: dict(a, header=np.array("[1, 2]")), "header must be a JSON object, got list"),
    "header_without_materials": (lambda a: dict(a, header=_header(materials=None)),
                                 "header must have the key 'materials'"),
    "material_not_an_object": (lambda a: dict(a, header=_header(materials=["wood"])),
                               "header materials[0] must be a JSON object"),
    "material_bad_value": (lambda a: dict(a, header=_header(materials=[{"reflectance": 7}])),
                           "materials[0]: Material 'default': reflectance must be a number in [0, 1], got 7"),
    "missing_vertices": (lambda a: _without(a, "vertices"), "must hold the array 'vertices'"),
    "missing_header": (lambda a: _without(a, "header"), "must hold the array 'header'"),
    "vertices_strings": (lambda a: dict(a, vertices=np.array(["a", "b", "c"])),
                         "vertices: must be a numeric array, got dtype <U1"),
    "vertices_wrong_shape": (lambda a: dict(a, vertices=np.zeros(5, np.float32)),
                             "vertices: must have shape (N, 3), got (5,)"),
    "triangles_out_of_range": (lambda a: dict(a, triangles=a["triangles"] + 10_000),
                               "triangles must index vertices in"),
    "object_array": (lambda a: dict(a, vertices=np.array([{"x": 1}], dtype=object)),
                     "array 'vertices' must be a numeric or string array (no Python objects), got dtype object"),
    "format_version_text": (lambda a: dict(a, format_version=np.array("one")), "format_version must be 1, got 'one'"),
    "texture_without_name": (lambda a: _without(a, "texture_name/0/roughness_texture"),
                             "array 'texture_name/0/roughness_texture' must be present"),
    "texture_of_no_material": (lambda a: dict(a, **{"texture/5/roughness_texture": np.ones((2, 2))}),
                               "array 'texture/5/roughness_texture' must be named texture/<material index < 1>"),
    "pose_not_a_matrix": (lambda a: dict(a, header=_header(metadata={"world_from_sensor": [[1, 2]]})),
                          "metadata.world_from_sensor must be a 4x4 matrix"),
    "pose_scaled": (lambda a: dict(a, header=_header(metadata={"world_from_sensor": (2 * np.eye(4)).tolist()})),
                    "header metadata.world_from_sensor must be a rigid transform: its rotation must be orthonormal "
                    "(no scale or shear), got axis lengths [2.0, 2.0, 2.0]"),
}


@pytest.mark.parametrize("case", sorted(BAD_SCENES))
def test_malformed_scene_file_is_one_line(tmp_path, capsys, case):
    change, needle = BAD_SCENES[case]
    path = write_npz(tmp_path / f"{case}.npz", change(good_arrays(textured=case.startswith("texture"))))
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    line = assert_refused(code, err, str(path), needle, out=tmp_path / "out")
    assert line.startswith(f"error: {path}: ")


def test_the_good_scene_file_of_these_tests_renders(tmp_path, capsys):
    """The cases above differ from a file that loads and renders in one thing each."""
    for textured in (False, True):
        path = write_npz(tmp_path / f"good_{textured}.npz", good_arrays(textured=textured))
        assert tofcore.Scene.load(path).triangle_count > 0
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert code == 0, err
    assert (tmp_path / "out" / "frame.json").is_file()


def _truncated(tmp_path: Path) -> Path:
    data = write_npz(tmp_path / "full.npz", good_arrays()).read_bytes()
    path = tmp_path / "truncated.npz"
    path.write_bytes(data[: len(data) // 2])
    return path


def _renamed_npy(tmp_path: Path) -> Path:
    path = tmp_path / "renamed.npz"
    path.write_bytes(_npy(np.zeros((4, 3), np.float32)))
    return path


def _random_bytes(tmp_path: Path) -> Path:
    path = tmp_path / "random.npz"
    path.write_bytes(np.random.default_rng(12).bytes(4096))
    return path


def _empty(tmp_path: Path) -> Path:
    path = tmp_path / "empty.npz"
    path.write_bytes(b"")
    return path


def _damaged_member(tmp_path: Path) -> Path:
    """A zip whose directory is intact but whose compressed vertices are garbage (CRC/zlib error)."""
    data = bytearray(write_npz(tmp_path / "full.npz", good_arrays()).read_bytes())
    with zipfile.ZipFile(tmp_path / "full.npz") as archive:
        info = archive.getinfo("vertices.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    rng = np.random.default_rng(3)
    data[start:start + info.compress_size] = rng.bytes(info.compress_size)
    path = tmp_path / "damaged.npz"
    path.write_bytes(bytes(data))
    return path


def _other_member(tmp_path: Path) -> Path:
    path = tmp_path / "other.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("readme.txt", "hello")
    return path


NOT_ZIPS = {
    "truncated": (_truncated, "a damaged or truncated zip archive"),
    "renamed_npy": (_renamed_npy, "got a single .npy array (numpy.save)"),
    "random_bytes": (_random_bytes, "a file that is not a zip archive"),
    "empty": (_empty, "got an empty file"),
    "damaged_member": (_damaged_member, "array 'vertices' cannot be read: the file is damaged or truncated"),
    "not_npy_member": (_other_member, "holding 'readme.txt', which is not a .npy array"),
}


@pytest.mark.parametrize("case", sorted(NOT_ZIPS))
def test_file_that_is_not_a_scene_is_one_line(tmp_path, capsys, case):
    make, needle = NOT_ZIPS[case]
    path = make(tmp_path)
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert_refused(code, err, f"error: {path}: must be a tofcore scene file" if case not in (
        "damaged_member",) else f"error: {path}: ", needle, out=tmp_path / "out")


def test_scene_file_errors_through_python_m_tofcore(tmp_path):
    """The real entry point, in a child process: the truncated file and a header that is not JSON."""
    bad_header = write_npz(tmp_path / "header.npz", dict(good_arrays(), header=np.array("{not json")))
    for path, needle in ((_truncated(tmp_path), "damaged or truncated zip"), (bad_header, "header must be")):
        code, err = run_subprocess(*render_args(tmp_path, scene=str(path)))
        assert_refused(code, err, str(path), needle, out=tmp_path / "out")


def test_zip_bomb_refused_from_the_zip_directory(tmp_path, capsys, monkeypatch):
    """A 60 MB array that deflates to ~60 kB: refused from the zip directory, before it is decompressed."""
    arrays = good_arrays()
    arrays["vertices"] = np.zeros((5_000_000, 3), np.float32)
    path = write_npz(tmp_path / "bomb.npz", arrays)
    assert path.stat().st_size < 200_000
    monkeypatch.setenv("TOFCORE_MAX_SCENE_BYTES", "1000000")
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert_refused(code, err, str(path), "array 'vertices' (uncompressed size from the zip directory) must be at "
                   "most 1,000,000 bytes", "TOFCORE_MAX_SCENE_BYTES=N", "got 60,000,128 bytes", out=tmp_path / "out")


def test_zip_directory_claiming_gigabytes_is_refused_at_the_default_limit(tmp_path, capsys):
    path = tmp_path / "dirlie.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, value in good_arrays().items():
            archive.writestr(f"{key}.npy", _npy(value))
        archive.filelist[-1].file_size = 10**10  # the directory says 10 GB
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert_refused(code, err, str(path), "must be at most 4,294,967,296 bytes (limit max_scene_bytes",
                   "got 10,000,000,000 bytes", out=tmp_path / "out")


def test_npy_header_claiming_gigabytes_is_refused_before_allocating(tmp_path, capsys):
    """A .npy header saying (5e9,) int8 in a member of a few bytes: refused, nothing allocated."""
    arrays = good_arrays()
    small = _npy(np.zeros(4, np.int8))
    lie = small.replace(b"(4,)", b"(5000000000,)")
    path = tmp_path / "hdrlie.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, value in arrays.items():
            archive.writestr(f"{key}.npy", lie if key == "vertices" else _npy(value))
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert_refused(code, err, str(path), "array 'vertices' (shape (5000000000,) x int8 from its .npy header) must "
                   "be at most 4,294,967,296 bytes", "TOFCORE_MAX_SCENE_BYTES", out=tmp_path / "out")


def test_npy_header_disagreeing_with_its_data_is_refused(tmp_path, capsys):
    arrays = good_arrays()
    lie = _npy(arrays["vertices"]).replace(f"({len(arrays['vertices'])}, 3)".encode(),
                                           f"({len(arrays['vertices']) + 7}, 3)".encode())
    path = tmp_path / "short.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key, value in arrays.items():
            archive.writestr(f"{key}.npy", lie if key == "vertices" else _npy(value))
    code, err = run(render_args(tmp_path, scene=str(path)), capsys)
    assert_refused(code, err, str(path), "array 'vertices' must hold the", "bytes its .npy header declares",
                   out=tmp_path / "out")


# --------------------------------------------------------------------------- class 2: resource limits

def test_huge_camera_in_a_preset_is_refused_while_loading_it(tmp_path, capsys):
    """100000 x 100000 px: refused before the camera's per-pixel tables (75 GiB) are built."""
    preset = tiny_preset(tmp_path, width="100000", height="100000")
    code, err = run(render_args(tmp_path, preset=str(preset)), capsys)
    assert_refused(code, err, f"{preset} [camera]: width x height must be at most 16,777,216 pixels",
                   "TOFCORE_MAX_PIXELS=N", "got 100000 x 100000 = 10,000,000,000", out=tmp_path / "out")


def test_pixel_limit_follows_its_environment_variable(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TOFCORE_MAX_PIXELS", "100")
    code, err = run(render_args(tmp_path), capsys)
    assert_refused(code, err, "[camera]: width x height must be at most 100 pixels", "got 16 x 12 = 192",
                   out=tmp_path / "out")
    monkeypatch.setenv("TOFCORE_MAX_PIXELS", "192")
    code, err = run(render_args(tmp_path), capsys)
    assert code == 0, err


def test_malformed_limit_variable_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TOFCORE_MAX_PIXELS", "lots")
    code, err = run(render_args(tmp_path), capsys)
    assert_refused(code, err, "TOFCORE_MAX_PIXELS must be a positive integer (pixels), got 'lots'",
                   out=tmp_path / "out")


def test_phase_steps_beyond_the_raw_image_limit(tmp_path, capsys):
    preset = tiny_preset(tmp_path, phase_steps="[3, 3, 1000000000]")
    code, err = run(render_args(tmp_path, preset=str(preset)), capsys)
    assert_refused(code, err, f"{preset} [modulation]: phase_steps (raw images per frame) must be at most 64",
                   "TOFCORE_MAX_RAW_IMAGES", "[3, 3, 1000000000]", out=tmp_path / "out")


@pytest.mark.parametrize("flag, value, needle", [
    ("--max-depth", "1000", "argument --max-depth: must be at most 64 surface vertices (limit max_depth; raise it "
                            "with the environment variable TOFCORE_MAX_DEPTH=N), got '1000'"),
    ("--spp", "1000000000", "argument --spp: must be at most 1,048,576 samples per pixel"),
])
def test_depth_and_spp_limits_are_argument_errors(tmp_path, capsys, flag, value, needle):
    code, err = run(render_args(tmp_path, flag, value), capsys)
    assert_refused(code, err, needle, out=tmp_path / "out")


def test_render_memory_estimate_is_checked_before_the_scene_is_loaded(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TOFCORE_MAX_RENDER_BYTES", "100000")
    code, err = run(render_args(tmp_path, "--max-depth", "20", scene=str(_empty(tmp_path))), capsys)
    assert_refused(code, err, "--max-depth 20: the estimated render memory (16 x 12 pixels, 9 raw images, max_depth "
                   "20) must be at most 100,000 bytes", "TOFCORE_MAX_RENDER_BYTES", out=tmp_path / "out")


def test_presets_command_checks_the_limits(capsys, monkeypatch):
    monkeypatch.setenv("TOFCORE_MAX_PIXELS", "1000")
    code, err = run(["presets"], capsys)
    assert_refused(code, err, "[camera]: width x height must be at most 1,000 pixels", "TOFCORE_MAX_PIXELS")


# --------------------------------------------------------------------------- class 3: flags and physics

@pytest.mark.parametrize("flag, value, needle", [
    ("--seed", "-1", "argument --seed: must be an integer >= 0, got '-1'"),
    ("--seed", "x1", "argument --seed: must be an integer >= 0, got 'x1'"),
    ("--spp", "0", "argument --spp: must be an integer >= 1, got '0'"),
    ("--spp", "2.5", "argument --spp: must be an integer >= 1, got '2.5'"),
    ("--max-depth", "-3", "argument --max-depth: must be an integer >= 1, got '-3'"),
    ("--time-budget", "-1", "argument --time-budget: must be a finite number > 0 (seconds), got '-1'"),
    ("--time-budget", "nan", "argument --time-budget: must be a finite number > 0 (seconds), got 'nan'"),
    ("--target-error", "inf", "argument --target-error: must be a length such as 5mm, 0.5cm or 0.005m (a bare number "
                              "is in mm), got 'inf'"),
    ("--target-error", "5 furlongs", "argument --target-error: must be a length such as 5mm"),
    ("--target-error", "-5mm", "argument --target-error: must be a length > 0 such as 5mm or 0.005m, got '-5mm'"),
    ("--ambient", "-1", "argument --ambient: must be a finite number >= 0, at most 1e+30 (W m^-2 sr^-1), got '-1'"),
    ("--ambient", "1e308", "argument --ambient: must be a finite number >= 0, at most 1e+30"),
    ("--formats", "exr,gif", "argument --formats: must be a comma list of one or more of exr, png, ply, json, "
                             "transient, got 'exr,gif' (unknown: 'gif')"),
    ("--formats", ",", "argument --formats: must be a comma list of one or more of exr, png, ply, json, transient, "
                       "got ',' (none given)"),
])
def test_bad_flag_is_an_argument_error(tmp_path, capsys, flag, value, needle):
    code, err = run(render_args(tmp_path, f"{flag}={value}"), capsys)
    assert_refused(code, err, needle, out=tmp_path / "out")


def test_bad_flags_through_python_m_tofcore(tmp_path):
    for flag, value in (("--seed", "-1"), ("--formats", "exr,gif"), ("--formats", ",")):
        code, err = run_subprocess(*render_args(tmp_path, f"{flag}={value}"))
        assert_refused(code, err, f"argument {flag}:", repr(value), out=tmp_path / "out")


def test_output_path_that_is_a_file_fails_before_rendering(tmp_path, capsys):
    (tmp_path / "out").write_text("a file")
    code, err = run(render_args(tmp_path), capsys)
    line = assert_refused(code, err, "--out: must be a folder, got the existing file")
    assert str(tmp_path / "out") in line


@pytest.mark.parametrize("replace, needle", [
    ({"responsivity": "1e300"}, "[readout]: responsivity must be at most 1e+30 (e-/s per W m^-2 sr^-1), got 1e+300"),
    ({"intensity_w_sr": "1e308"}, "[[leds]] #1: intensity_w_sr must be at most 1e+30 (W/sr), got 1e+308"),
    ({"full_well_e": "1e300"}, "[readout]: full_well_e must be at most 1e+30 (electrons), got 1e+300"),
    ({"exposure_s": "[8e-3, 4e-3, 1e300]"}, "[modulation]: exposure_s must be numbers <= 1e+30"),
    ({"read_noise_e": "1e300"}, "[noise]: read_noise_e must be at most 1e+30 (electrons), got 1e+300"),
])
def test_physics_that_would_overflow_names_the_preset_key(tmp_path, capsys, replace, needle):
    preset = tiny_preset(tmp_path, **replace)
    code, err = run(render_args(tmp_path, preset=str(preset)), capsys)
    assert_refused(code, err, f"error: {preset} ", needle, out=tmp_path / "out")


@pytest.mark.filterwarnings("ignore:overflow encountered in cast")  # the discarded amplitude of the clean decodes
def test_huge_but_allowed_physics_renders_finite(tmp_path, capsys):
    """At the ceiling the chain stays finite: pixels saturate (Poisson beyond NumPy's λ limit is Gaussian)."""
    preset = tiny_preset(tmp_path, responsivity="1e30", intensity_w_sr="1e30")
    code, err = run(render_args(tmp_path, preset=str(preset)), capsys)
    assert code == 0, err
    frame = tofcore.render(tofcore.demo_scene("plane"), tofcore.load_preset(preset), spp=1, max_depth=1, workers=1)
    for name in ("raw", "amplitude", "intensity", "offset", "gt_distance"):
        assert np.isfinite(getattr(frame, name)).all(), name
    assert (frame.reason[frame.gt_distance > 0] == tofcore.Reason.SATURATED).all()


def test_preset_that_is_not_a_file(tmp_path, capsys):
    for path, needle in ((tmp_path, "got a folder"), (Path("/dev/zero"), "got a special file")):
        if not path.exists():
            continue
        code, err = run(render_args(tmp_path, preset=str(path)), capsys)
        assert_refused(code, err, f"{path}: must be a preset .toml file", needle, out=tmp_path / "out")


# --------------------------------------------------------------------------- issue 23, class 5

@pytest.mark.parametrize("key", ["reflectance", "roughness", "metallic", "ior", "extinction"])
@pytest.mark.parametrize("value", [True, np.bool_(False)])
def test_a_material_refuses_booleans_as_numbers(key, value):
    with pytest.raises(tofcore.ConfigError, match=rf"Material 'm': {key} must be a number in \[.*\], got "
                                                  rf"{value!r}$"):
        tofcore.Material(name="m", **{key: value})


def test_an_aperture_wider_than_its_focus_distance_is_refused_naming_the_preset(tmp_path):
    preset = tmp_path / "lens.toml"
    preset.write_text(KINECT.replace("\nfx = ", "\naperture_radius_m = 1e6\nfocus_distance_m = 1e-9\nfx = ", 1))
    code, err = run_subprocess(*render_args(tmp_path, preset=str(preset)))
    assert_refused(code, err, f"{preset} [camera]: aperture_radius_m must be less than focus_distance_m",
                   "got 1000000.0 with focus_distance_m 1e-09", out=tmp_path / "out")


def test_an_extreme_focal_length_is_one_line_without_numpy_warnings(tmp_path):
    preset = tiny_preset(tmp_path, fx="1e-300", k1="0.09")
    code, err = run_subprocess(*render_args(tmp_path, preset=str(preset)))
    line = assert_refused(code, err, f"{preset} [camera]: distortion", out=tmp_path / "out")
    assert "RuntimeWarning" not in err and "fx=1e-300" in line
