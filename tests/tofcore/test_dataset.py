"""Dataset reader: listing and filters, lazy channel loads equal to read_exr, stacks, metadata, errors, torch adapter.

One tiny dataset is rendered per module by the batch generator in this
process (no worker processes): 2 scenes, 3 views, 2 presets = 6 frames at
1/32 resolution (Kinect v2: 16 × 13 px), 2 spp, max path length 2, one frame
failed on purpose.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import tofcore  # noqa: E402
from tofcore.output.dataset import CHANNELS, Dataset, DatasetError, FrameRef, Intrinsics  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
FAILED_LABEL = "box_on_wall/pose0/o3d303"

SET = """
seed = 5
presets = ["kinect_v2", "o3d303"]
resolution_scale = 0.03125
[quality]
spp = 2
max_depth = 2
[[scenes]]
demo = "corner"
[[scenes.poses]]
suggested = true
[[scenes.poses]]
eye = [1.2, 0.9, 1.3]
target = [0.0, 0.0, 1.2]
[[scenes]]
demo = "box_on_wall"
[[scenes.poses]]
suggested = true
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """The 6-frame dataset (5 ok, 1 failed); read-only for the tests (copy it to change it)."""
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from batch.jobs import expand
    from batch.run import run_jobs
    from batch.setfile import load_set

    folder = tmp_path_factory.mktemp("loader")
    set_file = folder / "set.toml"
    set_file.write_text(SET)
    with pytest.MonkeyPatch.context() as mp, open(os.devnull, "w") as devnull:
        mp.setenv("TOF_BATCH_FAIL", FAILED_LABEL)
        result = run_jobs(expand(load_set(set_file)).jobs, folder / "ds", inline=True, threads_per_worker=1,
                          quiet=True, stream=devnull)
    assert result.exit_code == 1  # the injected failure
    return folder / "ds"


@pytest.fixture
def copy(dataset, tmp_path) -> Path:
    """A copy of the dataset that a test may damage."""
    return Path(shutil.copytree(dataset, tmp_path / "ds"))


def _index(dataset: Path) -> list[dict]:
    return [json.loads(line) for line in (dataset / "index.jsonl").read_text().splitlines()]


def _document(ref: FrameRef) -> dict:
    return json.loads((ref.folder / "frame.json").read_text())


# --------------------------------------------------------------------------- listing

def test_frames_are_listed_in_index_order_with_their_record(dataset):
    data = Dataset(dataset)
    records = _index(dataset)
    assert len(records) == 6
    ok = [r for r in records if r["status"] == "ok"]
    assert len(data) == 5 and [f.id for f in data] == [r["job_id"] for r in ok]
    first = data[0]
    assert (first.id, first.scene, first.view, first.preset, first.seed, first.status) == (
        ok[0]["job_id"], ok[0]["scene"], ok[0]["view"]["label"], ok[0]["preset"], ok[0]["seed"], "ok")
    assert first.record == ok[0] and first.folder == dataset.resolve() / "frames" / first.id
    assert first.paths["exr"] == first.folder / "frame.exr" and first.paths["json"].is_file()
    assert data[first.id] is first and data.frame(first.id) is first
    assert data.scenes == ["corner", "box_on_wall"] and data.presets == ["kinect_v2", "o3d303"]
    assert data.views == ["pose0", "pose1"]


def test_frames_filter_by_scene_preset_view_and_status(dataset):
    data = Dataset(dataset)
    assert [(f.scene, f.preset) for f in data.frames(scene="corner")] == [
        ("corner", "kinect_v2"), ("corner", "o3d303"), ("corner", "kinect_v2"), ("corner", "o3d303")]
    assert {f.preset for f in data.frames(preset="o3d303")} == {"o3d303"}
    assert len(data.frames(preset="o3d303")) == 2  # the third is the failed one
    assert len(data.frames(scene="corner", preset="kinect_v2", view="pose1")) == 1
    assert len(data.frames(scene=["corner", "box_on_wall"])) == 5
    failed = data.frames(status="failed")
    assert [f"{f.scene}/{f.view}/{f.preset}" for f in failed] == [FAILED_LABEL]
    assert failed[0].paths == {} and "fault injected" in failed[0].record["error"]
    assert len(data.frames(status=None)) == len(data.frames(status=["ok", "failed"])) == 6


def test_a_filter_value_not_in_the_dataset_lists_the_valid_ones(dataset):
    data = Dataset(dataset)
    with pytest.raises(DatasetError) as exc:
        data.frames(scene="kitchen")
    assert _one_line(exc) == (f"{dataset.resolve()}: frames(scene=…): scene must be among ['corner', 'box_on_wall'], "
                              f"got 'kitchen'")
    with pytest.raises(DatasetError, match=r"status must be among \['ok', 'failed'\], got 'done'"):
        data.frames(status="done")
    with pytest.raises(DatasetError, match="no frame with id 'nope'"):
        data.frame("nope")


# --------------------------------------------------------------------------- loading

def test_load_returns_exactly_the_exr_channels_asked(dataset):
    ref = Dataset(dataset)[0]
    stored = tofcore.read_exr(ref.folder / "frame.exr")
    arrays = ref.load(["depth", "gt_depth", "valid", "reason"])
    assert list(arrays) == ["depth", "gt_depth", "valid", "reason"]
    for name, array in arrays.items():
        assert array.dtype == stored[name].dtype == np.float32 and array.shape == (13, 16)
        assert np.array_equal(array, stored[name], equal_nan=True), name
    assert list(ref.load("amplitude")) == ["amplitude"]
    everything = ref.load()
    assert set(everything) == {n for n in stored if not n.startswith(("raw.", "distance_k"))} | {
        "raw", "raw_labels", "distance_per_k"}
    for name in everything.keys() - {"raw", "raw_labels", "distance_per_k"}:
        assert np.array_equal(everything[name], stored[name], equal_nan=True), name


def test_invalid_pixels_stay_nan(dataset):
    for ref in Dataset(dataset):
        arrays = ref.load(["depth", "valid"])
        assert np.array_equal(np.isnan(arrays["depth"]), arrays["valid"] == 0)


def test_raw_images_are_stacked_in_label_order(dataset):
    data = Dataset(dataset)
    for ref in (data.frames(preset="kinect_v2")[0], data.frames(preset="o3d303")[0]):
        stored = tofcore.read_exr(ref.folder / "frame.exr")
        labels = tuple(_document(ref)["raw_labels"])
        arrays = ref.load(["raw"])
        assert arrays["raw_labels"] == labels == ref.raw_labels
        assert arrays["raw"].shape == (len(labels), ref.intrinsics.height, ref.intrinsics.width)
        for i, label in enumerate(labels):
            assert np.array_equal(arrays["raw"][i], stored[f"raw.{label}"])
    assert len(data.frames(preset="kinect_v2")[0].raw_labels) == 9  # 3 frequencies × 3 steps


def test_per_bounce_distances_are_stacked_k_1_to_K(dataset):
    ref = Dataset(dataset)[1]
    stored = tofcore.read_exr(ref.folder / "frame.exr")
    stack = ref.load("distance_per_k")["distance_per_k"]
    assert stack.shape[0] == _document(ref)["distance_per_k"] == 2  # max_depth 2
    for k in (1, 2):
        assert np.array_equal(stack[k - 1], stored[f"distance_k{k}"], equal_nan=True)


def test_intrinsics_and_pose_equal_frame_json(dataset):
    for ref in Dataset(dataset):
        document = _document(ref)
        expected = document["metadata"]["intrinsics"]
        intrinsics = ref.intrinsics
        assert isinstance(intrinsics, Intrinsics)
        assert (intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy) == (
            expected["width"], expected["height"], expected["fx"], expected["fy"], expected["cx"], expected["cy"])
        assert intrinsics.distortion == tuple(expected[k] for k in ("k1", "k2", "p1", "p2", "k3"))
        assert np.array_equal(intrinsics.matrix, [[expected["fx"], 0, expected["cx"]],
                                                  [0, expected["fy"], expected["cy"]], [0, 0, 1]])
        assert ref.world_from_sensor.shape == (4, 4) and ref.world_from_sensor.dtype == np.float64
        assert np.array_equal(ref.world_from_sensor, document["world_from_sensor"])
        assert np.array_equal(ref.world_from_sensor, ref.record["world_from_sensor"])
        assert ref.sensor["name"] == ref.preset


def test_ray_directions_times_distance_are_the_written_points(dataset):
    ref = Dataset(dataset).frames(preset="kinect_v2")[0]
    arrays = ref.load(["distance", "valid", "ray_directions"])
    valid = arrays["valid"] > 0.5
    assert arrays["ray_directions"].shape == (13, 16, 3) and valid.any()
    points = (arrays["ray_directions"] * arrays["distance"][..., None])[valid].astype(np.float32)
    ply = ref.paths["ply"].read_bytes()
    body = ply[ply.index(b"end_header\n") + len(b"end_header\n"):]
    vertices = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("amplitude", "<f4"), ("intensity", "u1")])
    assert np.allclose(vertices["xyz"], points, rtol=1e-6, atol=1e-6)


def test_sample_shapes_and_dtypes(dataset):
    ref = Dataset(dataset).frames(preset="kinect_v2")[0]
    sample = ref.sample(["depth", "valid", "reason", "object_id", "raw", "distance_per_k", "ray_directions"])
    shapes = {k: (v.shape, v.dtype.name) for k, v in sample.items() if isinstance(v, np.ndarray)}
    assert shapes == {
        "depth": ((1, 13, 16), "float32"), "valid": ((1, 13, 16), "bool"), "reason": ((1, 13, 16), "uint8"),
        "object_id": ((1, 13, 16), "int32"), "raw": ((9, 13, 16), "float32"),
        "distance_per_k": ((2, 13, 16), "float32"), "ray_directions": ((3, 13, 16), "float32"),
        "intrinsics": ((3, 3), "float32"), "distortion": ((5,), "float32"), "world_from_sensor": ((4, 4), "float32")}
    assert (sample["id"], sample["scene"], sample["view"], sample["preset"]) == (ref.id, ref.scene, ref.view,
                                                                                 ref.preset)
    assert np.array_equal(sample["valid"][0], ref.load("valid")["valid"] == 1)


def test_an_unknown_channel_lists_the_valid_names(dataset):
    ref = Dataset(dataset)[0]
    with pytest.raises(DatasetError, match=rf"frame {ref.id}: channels must be among .*, got unknown \['dpeth'\]"):
        ref.load(["depth", "dpeth"])
    assert "raw" in CHANNELS and "distance_per_k" in CHANNELS


# --------------------------------------------------------------------------- errors

def _one_line(exc: pytest.ExceptionInfo) -> str:
    message = str(exc.value)
    assert "\n" not in message
    return message


def test_a_folder_that_is_not_a_dataset_gives_one_line_naming_it(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(DatasetError) as exc:
        Dataset(missing)
    assert _one_line(exc) == f"{missing}: dataset folder not found"
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(DatasetError, match="must be a dataset folder, got a file") as exc:
        Dataset(tmp_path / "file.txt")
    assert str(tmp_path / "file.txt") in _one_line(exc)
    with pytest.raises(DatasetError, match=r"not a dataset folder \(no index.jsonl") as exc:
        Dataset(tmp_path)
    assert _one_line(exc).startswith(f"{tmp_path}: ")
    (tmp_path / "index.jsonl").write_text("")
    with pytest.raises(DatasetError, match=r"no frames/ beside index.jsonl"):
        Dataset(tmp_path)
    assert issubclass(DatasetError, tofcore.ConfigError)


def test_lines_that_are_not_records_are_skipped_with_a_warning(copy):
    index = copy / "index.jsonl"
    lines = index.read_text().splitlines()
    lines[1:1] = ["not json at all", '{"status": "ok"}', "[1, 2]", '{"job_id": 7}', "", '{"job_id": "cut", "sta']
    index.write_text("\n".join(lines) + "\n")
    with pytest.warns(UserWarning, match=r"index.jsonl: skipped 5 line\(s\) that are not frame records "
                                         r"\(line 2, 3, 4, 5, 7\)"):
        data = Dataset(copy)
    assert len(data.frames(status=None)) == 6 and len(data) == 5 and data.skipped_lines == [2, 3, 4, 5, 7]


def test_a_later_line_of_a_job_replaces_the_earlier_one(copy):
    index = copy / "index.jsonl"
    records = _index(copy)
    earlier = dict(records[0], status="failed", error="an earlier attempt")
    index.write_text("".join(json.dumps(r) + "\n" for r in [earlier, *records[1:], records[0]]))
    data = Dataset(copy)
    assert len(data.frames(status=None)) == 6 and data.frame(records[0]["job_id"]).status == "ok"
    assert data.frames(status=None)[-1].id == records[0]["job_id"]


def test_a_missing_frame_file_names_it(copy):
    data = Dataset(copy)
    ref = data[0]
    (ref.folder / "frame.exr").unlink()
    with pytest.raises(DatasetError) as exc:
        ref.load(["depth"])
    assert _one_line(exc).startswith(f"{ref.folder / 'frame.exr'}: frame file not found")
    other = data[1]
    (other.folder / "frame.json").unlink()
    with pytest.raises(DatasetError, match="frame.json: frame file not found"):
        other.intrinsics
    exr = data[3].folder / "frame.exr"
    exr.write_bytes(b"not an EXR".ljust(exr.stat().st_size, b"!"))  # the size the record says: only read_exr sees it
    with pytest.raises(DatasetError, match=r"frame.exr: cannot be read as EXR") as exc:
        Dataset(copy, checksum="size")[3].load("depth")
    assert str(data[3].folder) in _one_line(exc)
    shutil.rmtree(data[2].folder)
    with pytest.raises(DatasetError, match=f"{data[2].id}/frame.exr: frame file not found"):
        data[2].load("depth")


def test_a_failed_frame_cannot_be_loaded_and_says_why(dataset):
    failed = Dataset(dataset).frames(status="failed")[0]
    with pytest.raises(DatasetError, match=rf"frame {failed.id}: status 'failed', no files \(error: .*fault injected"):
        failed.load("depth")


def _record_files_again(dataset: Path, job_id: str) -> None:
    """Rewrite a frame's record.json and index line for its files as they are now (sizes, SHA-256)."""
    import hashlib

    folder = dataset / "frames" / job_id
    record = json.loads((folder / "record.json").read_bytes())
    for entry in record["files"]:
        data = (folder / entry["name"]).read_bytes()
        entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    data = (json.dumps(record, indent=1) + "\n").encode()
    (folder / "record.json").write_bytes(data)
    line = {**record, "record_file": {"kind": "record", "name": "record.json", "bytes": len(data),
                                      "sha256": hashlib.sha256(data).hexdigest()}}
    _write_index(dataset, [line if r["job_id"] == job_id else r for r in _index(dataset)])


def test_a_channel_missing_from_the_file_names_file_and_channels(copy):
    ref = Dataset(copy)[0]
    stored = tofcore.read_exr(ref.folder / "frame.exr")
    del stored["render_error"]
    tofcore.exr.write(ref.folder / "frame.exr", stored)
    _record_files_again(copy, ref.id)  # an older frame, as its record describes it
    ref = Dataset(copy).frame(ref.id)
    with pytest.raises(DatasetError, match=r"frame.exr: channel 'render_error' not in the file; it holds \['ampl"):
        ref.load(["render_error"])
    assert "render_error" not in ref.load()


# --------------------------------------------------------------------------- PyTorch adapter

def test_importing_tofcore_and_the_reader_imports_neither_torch_nor_batch():
    code = ("import sys, tofcore, tofcore.output.dataset; "
            "print(sorted(m for m in ('torch', 'batch', 'bpy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO / "tests",
                         check=True).stdout
    assert out.strip() == "[]"


def test_the_torch_adapter_without_torch_says_so_in_one_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.delitem(sys.modules, "tofcore.output.torch_dataset", raising=False)
    with pytest.raises(ImportError, match=r"^tofcore.output.torch_dataset: needs PyTorch, which is not installed: "
                                          r"pip install torch") as exc:
        import tofcore.output.torch_dataset  # noqa: F401
    assert _one_line(exc)


def _fake_torch() -> types.ModuleType:
    """Just enough of torch for the adapter: a Dataset base class and from_numpy (tagging the array)."""
    torch = types.ModuleType("torch")
    torch.utils = types.ModuleType("torch.utils")
    torch.utils.data = types.ModuleType("torch.utils.data")
    torch.utils.data.Dataset = type("Dataset", (), {})
    torch.from_numpy = lambda array: ("tensor", array)
    return torch


def test_the_torch_adapter_logic_on_a_stand_in_torch(dataset, monkeypatch):
    fake = _fake_torch()
    for name, module in (("torch", fake), ("torch.utils", fake.utils), ("torch.utils.data", fake.utils.data)):
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.delitem(sys.modules, "tofcore.output.torch_dataset", raising=False)
    from tofcore.output.torch_dataset import TorchDataset

    data = TorchDataset(dataset, channels=["depth", "valid", "raw"], preset="kinect_v2",
                        transform=lambda s: {**s, "seen": True})
    assert isinstance(data, fake.utils.data.Dataset) and len(data) == 3
    sample = data[0]
    assert sample["seen"] and sample["id"] == data.refs[0].id and isinstance(sample["scene"], str)
    assert {k for k, v in sample.items() if isinstance(v, tuple) and v[0] == "tensor"} == {
        "depth", "valid", "raw", "intrinsics", "distortion", "world_from_sensor"}
    assert sample["raw"][1].shape == (9, 13, 16) and sample["valid"][1].dtype == bool
    monkeypatch.delitem(sys.modules, "tofcore.output.torch_dataset")


def test_the_torch_adapter_with_torch(dataset):
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader

    from tofcore.output.torch_dataset import TorchDataset

    data = TorchDataset(dataset, channels=["depth", "gt_depth", "valid", "raw"], preset="kinect_v2")
    batch = next(iter(DataLoader(data, batch_size=2)))
    assert batch["depth"].shape == (2, 1, 13, 16) and batch["depth"].dtype == torch.float32
    assert batch["valid"].dtype == torch.bool and batch["raw"].shape == (2, 9, 13, 16)
    assert batch["intrinsics"].shape == (2, 3, 3) and batch["world_from_sensor"].shape == (2, 4, 4)
    assert batch["id"] == [data.refs[0].id, data.refs[1].id]


# --------------------------------------------------------------------------- what the reader checks (issue 23)

def _write_index(dataset: Path, records: list[dict]) -> None:
    (dataset / "index.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))


def test_a_frame_exr_replaced_by_another_frames_is_refused_when_loaded(copy):
    data = Dataset(copy)
    first, second = data[0], data[1]
    shutil.copyfile(second.folder / "frame.exr", first.folder / "frame.exr")
    with pytest.raises(DatasetError) as exc:
        first.load("depth")
    message = _one_line(exc)
    assert message.startswith(f"{first.folder / 'frame.exr'}: ") and "frame's record" in message
    assert second.load("depth")["depth"].shape == (second.intrinsics.height, second.intrinsics.width)


def test_a_file_replaced_by_one_of_the_same_size_is_seen_by_its_checksum_unless_only_sizes_are_asked(copy):
    ref = Dataset(copy)[0]
    document = json.loads((ref.folder / "frame.json").read_bytes())
    fx = document["metadata"]["intrinsics"]["fx"]
    text = (ref.folder / "frame.json").read_text()
    doubled = text.replace(f'"fx": {json.dumps(fx)}', f'"fx": {json.dumps(fx * 2)}', 1)
    assert doubled != text
    (ref.folder / "frame.json").write_text(doubled)
    with pytest.raises(DatasetError, match=r"frame.json: (SHA-256 differs|\d+ bytes, the frame's record says)"):
        ref.intrinsics


def test_a_symlinked_frame_folder_is_refused_with_a_warning(copy):
    records = [r for r in _index(copy) if r["status"] == "ok"]
    target = copy / "frames" / records[0]["job_id"]
    shutil.rmtree(target)
    target.symlink_to(copy / "frames" / records[1]["job_id"])
    with pytest.warns(UserWarning, match=r"1 frame\(s\) refused: .*a symbolic link, not a frame folder"):
        data = Dataset(copy)
    assert len(data) == 4 and records[0]["job_id"] in data.refused
    with pytest.raises(DatasetError, match=f"frame {records[0]['job_id']}: refused"):
        data.frame(records[0]["job_id"])


@pytest.mark.parametrize("changes, key", [
    ({"scene": "box_on_wall"}, "scene"),
    ({"status": "failed"}, "status"),
    ({"world_from_sensor": [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "world_from_sensor"),
])
def test_an_edited_index_line_is_replaced_by_the_frames_record_with_a_warning(copy, changes, key):
    records = _index(copy)
    truth = records[0]
    records[0] = {**truth, **changes}
    _write_index(copy, records)
    with pytest.warns(UserWarning, match=rf"1 line\(s\) differ from their frame's record.json, which is used: "
                                         rf"line 1 \({key}\)"):
        data = Dataset(copy)
    ref = data.frame(truth["job_id"])
    assert (ref.scene, ref.status) == (truth["scene"], "ok")
    assert ref.record["world_from_sensor"] == truth["world_from_sensor"]
    assert [f.id for f in data.frames(scene="corner")][0] == truth["job_id"]


@pytest.mark.parametrize("keep", [0, 3])
def test_frame_folders_the_index_does_not_list_are_counted_in_a_warning(copy, keep):
    records = [r for r in _index(copy) if r["status"] == "ok"]
    _write_index(copy, records[:keep])
    with pytest.warns(UserWarning, match=rf"{5 - keep} frame folder\(s\) in frames/ are not in index.jsonl"):
        data = Dataset(copy)
    assert len(data) == keep and len(data.unindexed) == 5 - keep


def test_the_torch_adapter_refuses_mixed_presets_in_one_line(dataset, monkeypatch):
    """torch's default collate would fail inside the DataLoader (stack expects each tensor to be equal size);
    the adapter says so when it is made, naming the groups and the filter that picks one."""
    fake = _fake_torch()
    for name, module in (("torch", fake), ("torch.utils", fake.utils), ("torch.utils.data", fake.utils.data)):
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.delitem(sys.modules, "tofcore.output.torch_dataset", raising=False)
    from tofcore.output.torch_dataset import TorchDataset

    with pytest.raises(ValueError) as info:
        TorchDataset(dataset, channels=["depth"])
    message = str(info.value)
    assert "\n" not in message and "frames of 2 presets or sizes cannot be stacked" in message
    assert "kinect_v2 16x13 (3 frames)" in message and "o3d303 11x8 (2 frames)" in message
    assert "preset='kinect_v2'" in message
    assert len(TorchDataset(dataset, channels=["depth"], allow_mixed=True)) == 5
    monkeypatch.delitem(sys.modules, "tofcore.output.torch_dataset")


def test_object_ids_have_names_and_materials_in_the_record_frame_json_and_reader(dataset):
    data = Dataset(dataset)
    for ref in data.frames():
        names = {entry["id"]: entry["name"] for entry in ref.record["objects"]}
        assert ref.record["objects"] == _document(ref)["metadata"]["objects"]
        assert {i: o["name"] for i, o in ref.objects.items()} == names
        scene = tofcore.demo_scene(ref.scene)
        assert [names[i] for i in sorted(names)] == list(scene.object_names)
        ids = ref.load("object_id")["object_id"]
        seen = set(np.unique(ids[ids >= 0]).astype(int).tolist())
        assert seen and seen <= set(names)            # every id in the image has a name
        for i, entry in ref.objects.items():          # and its materials are the scene's, by name
            used = np.unique(scene.material_ids[scene.object_ids == i])
            assert entry["materials"] == [scene.materials[m].name for m in used]


def test_a_frame_without_a_transient_histogram_says_how_to_get_one(dataset):
    ref = Dataset(dataset).frames()[0]
    with pytest.raises(DatasetError, match=r"no transient histogram \(set \[output\] transient_bin_m"):
        ref.transient


# --------------------------------------------------------------------------- hostile frame files (issue 35)

def _zip_bomb_first_chunk(path: Path, mib: int) -> None:
    """Point the first chunk of ``path``'s offset table at a new chunk, appended, whose zlib stream inflates
    to ``mib`` MiB (the chunk's lines hold a few kB)."""
    import struct
    import zlib

    data = path.read_bytes()
    end = tofcore.exr._Reader(data, str(path)).header()[1]
    y = struct.unpack("<i", data[int.from_bytes(data[end:end + 8], "little"):][:4])[0]
    packer = zlib.compressobj(9)
    stream = b"".join(packer.compress(bytes(1 << 20)) for _ in range(mib)) + packer.flush()
    path.write_bytes(data[:end] + struct.pack("<Q", len(data)) + data[end + 8:] + struct.pack("<ii", y, len(stream))
                     + stream)


def test_a_zip_bomb_in_frame_exr_is_one_line_in_bounded_memory(copy):
    import tracemalloc

    ref = Dataset(copy)[0]
    _zip_bomb_first_chunk(ref.folder / "frame.exr", 64)
    _record_files_again(copy, ref.id)
    ref = Dataset(copy).frame(ref.id)
    tracemalloc.start()
    try:
        with pytest.raises(DatasetError) as exc:
            ref.load(["depth"])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = _one_line(exc)
    assert message.startswith(f"{ref.folder / 'frame.exr'}: cannot be read as EXR: damaged EXR: a ZIP chunk "
                              f"inflates to more than the "), message
    assert peak < 16 << 20, peak  # the old reader inflated all 64 MiB


def test_a_uint_typed_depth_channel_is_refused_in_one_line(copy):
    ref = Dataset(copy)[0]
    stored = tofcore.exr.read(ref.folder / "frame.exr")
    stored["depth"] = np.nan_to_num(stored["depth"] * 1000).astype(np.uint32)  # millimetres as integers
    tofcore.exr.write(ref.folder / "frame.exr", stored)
    _record_files_again(copy, ref.id)
    with pytest.raises(DatasetError) as exc:
        Dataset(copy).frame(ref.id).load(["depth"])
    assert _one_line(exc) == (f"{ref.folder / 'frame.exr'}: cannot be read as EXR: channels ['depth'] are UINT "
                              f"(integers); a tofcore frame's channels are FLOAT or HALF (metres, electrons, 0/1 "
                              f"masks)")
