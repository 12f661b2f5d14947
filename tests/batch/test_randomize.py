"""batch.randomize and batch.distributions: randomized views in set files, seeded, recorded, with labels."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from batch import distributions as dists
from batch.jobs import expand, group_by_view
from batch.randomize import build_view, vary_sensor
from batch.run import run_jobs
from batch.setfile import SetFileError, load_set
from batch_helpers import TINY, frame_arrays, read_index, write_set

#: A tiny randomized room: 2 views, objects, materials by class, ambient, orbit camera and sensor unit.
RANDOM_SET = """
seed = 11
presets = ["kinect_v2"]
""" + TINY + """
[output]
formats = ["exr", "json"]
labels = true
[[scenes]]
demo = "room"
[scenes.randomize]
count = 2
[scenes.randomize.objects]
shapes = ["box", "cylinder", "sphere"]
count = { dist = "uniform", low = 2, high = 4 }
size_m = { dist = "uniform", low = 0.2, high = 0.4 }
[scenes.randomize.materials.objects]
match = ["box", "cylinder", "sphere"]
reflectance = { dist = "uniform", low = 0.2, high = 0.9 }
metallic = { dist = "choice", values = [0.0, 1.0], weights = [0.5, 0.5] }
[scenes.randomize.materials.room]
match = ["walls", "floor"]
roughness = { dist = "normal", mean = 0.4, std = 0.1 }
[scenes.randomize.camera]
distance_m = { dist = "uniform", low = 1.0, high = 2.0 }
[scenes.randomize.ambient]
radiance_w_m2_sr = { dist = "loguniform", low = 0.001, high = 0.1 }
[scenes.randomize.sensor]
"camera.fx" = { dist = "normal", mean = 1.0, std = 0.02, apply = "scale" }
"leds.position_m" = { dist = "uniform", low = -0.003, high = 0.003, apply = "offset" }
"""


@pytest.fixture(scope="module")
def random_set(tmp_path_factory) -> Path:
    return write_set(tmp_path_factory.mktemp("randomize"), RANDOM_SET)


@pytest.fixture(scope="module")
def rendered(random_set, tmp_path_factory) -> Path:
    """The randomized set rendered once in this process."""
    out = tmp_path_factory.mktemp("randomized") / "data"
    result = run_jobs(expand(load_set(random_set)).jobs, out, inline=True, threads_per_worker=1, quiet=True,
                      stream=open(os.devnull, "w"))
    assert result.exit_code == 0
    return out


# --------------------------------------------------------------------------- distributions

def _fail(key, rule, value):
    return ValueError(f"{key}: must be {rule}, got {value!r}")


@pytest.mark.parametrize("table", [
    {"dist": "uniform", "low": 0.2, "high": 0.9},
    {"dist": "loguniform", "low": 0.01, "high": 1.0},
    {"dist": "normal", "mean": 0.3, "std": 0.2},           # truncated to the valid range [0, 1]
    {"dist": "normal", "mean": 0.5, "std": 0.1, "low": 0.45, "high": 0.7},
])
def test_draws_follow_the_stated_distribution(table):
    """Kolmogorov–Smirnov: n = 4000 draws against the stated cdf (truncation included); at α = 0.001 the
    critical distance is 1.95/√n = 0.031. A log-uniform drawn uniformly (or an untruncated normal)
    lies 0.2–0.4 away."""
    dist = dists.parse(table, "x", _fail, (0.0, 1.0))
    rng = np.random.default_rng(5)
    x = np.sort([dist.sample(rng) for _ in range(4000)])
    n = len(x)
    cdf = dist.cdf(x)
    ks = max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n))
    assert ks < 1.95 / math.sqrt(n)
    assert x.min() >= max(dist.low, 0.0) and x.max() <= min(dist.high, 1.0)


def test_choice_follows_its_weights():
    """χ² with 2 degrees of freedom, n = 6000: below 13.8 (α = 0.001); equal weights would give ~900."""
    dist = dists.parse({"dist": "choice", "values": [0.0, 0.5, 1.0], "weights": [6, 3, 1]}, "x", _fail)
    rng = np.random.default_rng(9)
    draws = np.array([dist.sample(rng) for _ in range(6000)])
    observed = np.array([(draws == v).sum() for v in (0.0, 0.5, 1.0)])
    expected = 6000 * np.array([0.6, 0.3, 0.1])
    assert ((observed - expected) ** 2 / expected).sum() < 13.8


@pytest.mark.parametrize("snippet, message", [
    ('reflectance = { dist = "uniform", low = 0.2, high = 1.5 }',
     r"set.toml:\d+: scenes\[0\]\.randomize\.materials\.walls\.reflectance\.high: must be within the valid range "
     r"\[0, 1\] \(1\), got 1\.5"),
    ('reflectance = { dist = "gauss", mean = 0.5 }',
     r"set.toml:\d+: scenes\[0\]\.randomize\.materials\.walls\.reflectance\.dist: must be one of \['uniform', "
     r"'normal', 'loguniform', 'choice'\], got 'gauss'"),
    ('roughness = { dist = "normal", mean = 0.4 }',
     r"materials\.walls\.roughness\.std: must be given"),
    ('roughness = { dist = "loguniform", low = 0.0, high = 0.5 }',
     r"materials\.walls\.roughness\.low: must be a number > 0 \(a log-uniform distribution\), got 0\.0"),
    ('metallic = { dist = "choice", values = [0.0, 1.0], weights = [1.0] }',
     r"materials\.walls\.metallic\.weights: must be 2 finite numbers >= 0"),
    ('shine = 0.5', r"materials\.walls\.shine: unknown key 'shine'"),
])
def test_bad_material_distributions_name_file_line_and_key(tmp_path, snippet, message):
    body = RANDOM_SET.replace('[scenes.randomize.materials.room]', f'[scenes.randomize.materials.walls]\n{snippet}\n'
                                                                    f'[scenes.randomize.materials.room]')
    with pytest.raises(SetFileError, match=message):
        load_set(write_set(tmp_path, body))


@pytest.mark.parametrize("old, new, message", [
    ('"camera.fx" = { dist = "normal", mean = 1.0, std = 0.02, apply = "scale" }',
     '"camera.width" = { dist = "uniform", low = 1, high = 2, apply = "scale" }',
     r"randomize\.sensor\.camera\.width: must name a float field of the preset 'kinect_v2'"),
    ('"camera.fx" = { dist = "normal", mean = 1.0, std = 0.02, apply = "scale" }',
     '"camera.fx" = { dist = "normal", mean = 1.0, std = 0.02 }',
     r"randomize\.sensor\.camera\.fx: must be a distribution table with apply"),
    ('"camera.fx" = { dist = "normal", mean = 1.0, std = 0.02, apply = "scale" }',
     '"noise.read_noise_e" = { dist = "uniform", low = -50.0, high = 0.0, apply = "offset" }',
     r"randomize\.sensor\.noise\.read_noise_e: the draw -50 \(offset\) makes the preset 'kinect_v2' invalid"),
    ('distance_m = { dist = "uniform", low = 1.0, high = 2.0 }', 'look_at = "table"',
     r"randomize\.camera\.look_at: must be \"object\" or \"scene\", got 'table'"),
    ('shapes = ["box", "cylinder", "sphere"]', 'shapes = ["box", "torus"]',
     r"randomize\.objects\.shapes: must be a list of primitive names"),
])
def test_bad_randomize_tables_name_the_key(tmp_path, old, new, message):
    with pytest.raises(SetFileError, match=message):
        load_set(write_set(tmp_path, RANDOM_SET.replace(old, new)))


# --------------------------------------------------------------------------- seeds

def test_a_view_seed_reproduces_its_draws_and_another_seed_changes_them(random_set):
    import tofcore

    spec = load_set(random_set).scenes[0].randomize
    base = tofcore.demo_scene("room")
    scene_a, pose_a, ambient_a, drawn_a = build_view(base, spec, 1234)
    scene_b, pose_b, ambient_b, drawn_b = build_view(base, spec, 1234)
    assert drawn_a == drawn_b and np.array_equal(pose_a, pose_b)
    assert np.array_equal(scene_a.vertices, scene_b.vertices) and scene_a.object_names == scene_b.object_names
    assert [m.to_dict() for m in scene_a.materials] == [m.to_dict() for m in scene_b.materials]
    assert ambient_a.radiance_w_m2_sr == ambient_b.radiance_w_m2_sr == drawn_a["ambient"]["radiance_w_m2_sr"]
    _, pose_c, _, drawn_c = build_view(base, spec, 1235)
    assert drawn_c["camera"] != drawn_a["camera"] and not np.array_equal(pose_c, pose_a)
    # What was drawn is what the scene holds.
    walls = next(m for m in scene_a.materials if m.name == "walls")
    assert walls.roughness == next(d["roughness"] for d in drawn_a["materials"] if d["material"] == "walls")
    assert len(scene_a.object_names) == len(base.object_names) + drawn_a["objects"]["placed"]
    assert np.allclose(pose_a[:3, 3], drawn_a["camera"]["eye_m"])


def test_job_ids_and_view_seeds_do_not_depend_on_the_run(random_set):
    first, second = expand(load_set(random_set)).jobs, expand(load_set(random_set)).jobs
    assert [j.job_id for j in first] == [j.job_id for j in second] and len(first) == 2
    seeds = [j.view["randomize_seed"] for j in first]
    assert len(set(seeds)) == 2
    tasks = group_by_view(first)
    assert len(tasks) == 2 and all(t.randomize is not None for t in tasks)
    # More views keep the first ones (their ids and seeds); another table draws other frames.
    grown = expand(load_set(write_set(random_set.parent, RANDOM_SET.replace("count = 2\n", "count = 3\n", 1),
                                      "grown.toml"))).jobs
    assert [j.job_id for j in grown[:2]] == [j.job_id for j in first] and len(grown) == 3
    other = expand(load_set(write_set(random_set.parent, RANDOM_SET.replace("high = 2.0 }", "high = 2.1 }"),
                                      "other.toml"))).jobs
    assert not {j.job_id for j in other} & {j.job_id for j in first}


def test_the_sensor_unit_is_drawn_from_the_frame_seed(random_set):
    job = expand(load_set(random_set)).jobs[0]
    a, draws_a = vary_sensor(job.sensor, job.randomize["sensor"], job.seed)
    b, draws_b = vary_sensor(job.sensor, job.randomize["sensor"], job.seed)
    assert a == b and draws_a == draws_b
    assert a["camera"]["fx"] == pytest.approx(job.sensor["camera"]["fx"] * draws_a["camera.fx"]["draw"], rel=1e-12)
    shift = np.subtract(a["leds"][0]["position_m"], job.sensor["leds"][0]["position_m"])
    assert np.allclose(shift, draws_a["leds.position_m"]["draw"]) and np.all(np.abs(shift) <= 0.003)
    c, _ = vary_sensor(job.sensor, job.randomize["sensor"], job.seed + 1)
    assert c["camera"]["fx"] != a["camera"]["fx"]


# --------------------------------------------------------------------------- rendered frames

def test_a_rerun_reproduces_parameters_and_pixels(random_set, rendered, tmp_path):
    again = tmp_path / "again"
    result = run_jobs(expand(load_set(random_set)).jobs, again, inline=True, threads_per_worker=1, quiet=True,
                      stream=open(os.devnull, "w"))
    assert result.exit_code == 0
    first = {r["job_id"]: r for r in read_index(rendered)}
    for record in read_index(again):
        old = first[record["job_id"]]
        assert record["randomization"] == old["randomization"]
        # Pixels bit for bit (frame.exr's header holds the render time, so its bytes differ).
        a, b = frame_arrays(again, record), frame_arrays(rendered, old)
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)
        name = "labels.npz"
        assert (again / record["dir"] / name).read_bytes() == (rendered / old["dir"] / name).read_bytes()


def test_records_and_frame_json_hold_the_draws_and_the_unit(rendered):
    import json

    for record in read_index(rendered):
        drawn = record["randomization"]
        assert {"seed", "objects", "materials", "ambient", "camera", "sensor"} <= drawn.keys()
        document = json.loads((rendered / record["dir"] / "frame.json").read_text())
        assert document["metadata"]["randomization"] == drawn
        fx = document["metadata"]["sensor"]["camera"]["fx"]
        assert fx == pytest.approx(365.402802 * 0.0625 * drawn["sensor"]["camera.fx"]["draw"], rel=1e-9)
        assert record["world_from_sensor"][0][3] == pytest.approx(drawn["camera"]["eye_m"][0], abs=1e-9)


def test_labels_are_what_the_frame_says_and_the_loader_returns_them(rendered):
    from tofcore.output.dataset import Dataset

    data = Dataset(rendered)
    assert len(data) == 2
    for ref in data:
        arrays = ref.load(["depth", "gt_depth", "valid", "direct_distance", "object_id", "ray_directions",
                           "multipath_error", "direct_depth", "normal", "material_id"])
        valid = arrays["valid"] > 0.5
        expected = np.where(valid, arrays["depth"] - arrays["gt_depth"], np.nan)
        assert np.array_equal(np.isnan(arrays["multipath_error"]), np.isnan(expected))
        assert np.allclose(arrays["multipath_error"][valid], expected[valid], atol=1e-6)
        # z-depth output: direct depth = direct radial distance × the ray's z (the Kinect v2 reports z).
        z = arrays["direct_distance"] * arrays["ray_directions"][..., 2]
        assert np.allclose(arrays["direct_depth"], z, atol=1e-5, equal_nan=True)
        hit = arrays["object_id"] >= 0
        assert np.array_equal(arrays["material_id"] >= 0, hit)
        normal = arrays["normal"][hit]
        assert np.allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", normal, arrays["ray_directions"][hit]) <= 1e-6)  # faces the camera
        assert set(np.unique(arrays["material_id"][hit]).tolist()) <= set(ref.materials)
        # The camera looks at the centre of its target object: the middle pixels see it.
        target = ref.randomization["camera"]["target_object"]
        h, w = arrays["object_id"].shape
        middle = arrays["object_id"][h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1]
        assert target in {ref.objects[int(i)]["name"] for i in middle.ravel() if i >= 0}
        sample = ref.sample(["normal", "material_id", "multipath_error"])
        assert sample["normal"].shape == (3, h, w) and sample["material_id"].dtype == np.int32


def test_the_card_shows_histograms_of_the_draws(rendered):
    card = (rendered / "README.md").read_text()
    assert "## Diversity" in card
    pictures = [line.split("](", 1)[1].rstrip(")") for line in card.splitlines() if line.startswith("![")]
    names = {Path(p).name for p in pictures if p.startswith("card/")}
    assert {"frame.valid_fraction.png", "frame.multipath_rms_m.png", "camera.distance_m.png", "objects.size_m.png",
            "material.objects.reflectance.png", "sensor.camera.fx_scale_.png"} <= names
    for picture in pictures:
        assert (rendered / picture).read_bytes().startswith(b"\x89PNG")
    assert "| camera.distance_m | 2 |" in card


# --------------------------------------------------------------------------- folders: textures, maps, meshes

_TETRAHEDRON_OBJ = """o tetra
v 0 0 0
v 1 0 0
v 0 0 -1
v 0 1 0
f 1 3 2
f 1 2 4
f 1 4 3
f 2 3 4
"""


def test_textures_environment_maps_and_library_meshes_come_from_folders(tmp_path):
    import tofcore

    (tmp_path / "textures").mkdir()
    stripes = np.tile(np.array([0.2, 0.8], np.float32), (8, 4))
    np.save(tmp_path / "textures" / "stripes.npy", stripes)
    (tmp_path / "sky").mkdir()
    np.save(tmp_path / "sky" / "flat.npy", np.full((4, 8), 0.05, np.float32))
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "tetra.obj").write_text(_TETRAHEDRON_OBJ)
    body = RANDOM_SET.replace('shapes = ["box", "cylinder", "sphere"]', 'library = "meshes"').replace(
        'match = ["walls", "floor"]', 'match = ["walls", "floor"]\ntextures = "textures"\ntexture_probability = 1.0'
    ).replace('radiance_w_m2_sr = { dist = "loguniform", low = 0.001, high = 0.1 }',
              'environments = "sky"\nenvironment_strength = { dist = "uniform", low = 0.5, high = 2.0 }')
    spec = load_set(write_set(tmp_path, body)).scenes[0].randomize
    assert spec["objects"]["library"]["files"][0][0] == "tetra.obj"
    scene, pose, ambient, drawn = build_view(tofcore.demo_scene("room"), spec, 77)
    frame = tofcore.render(scene, tofcore.load_preset("kinect_v2").scaled(0.0625), pose, spp=1, max_depth=1,
                           ambient=ambient, seed=1)
    assert frame.valid.mean() > 0.5 and frame.material_id is not None
    walls = next(m for m in scene.materials if m.name == "walls")
    record = next(d for d in drawn["materials"] if d["material"] == "walls")
    assert record["texture"] == "stripes.npy" and walls.reflectance_texture is not None
    # The stripes about the walls' reflectance (their own 0.7: the class draws no reflectance), in [0, 1]:
    # 0.2/0.8 about 0.5 → contrast min(1, 0.7/0.3, 0.3/0.3) = 1 → 0.4/1.0.
    assert walls.reflectance_texture.data.mean() == pytest.approx(0.7, rel=1e-6)
    assert np.allclose(np.unique(walls.reflectance_texture.data), [0.4, 1.0])
    assert scene.uvs is not None and scene.uvs.shape == (len(scene.vertices), 2)  # box-projected for the room
    assert drawn["ambient"]["environment"] == "flat.npy" and 0.5 <= drawn["ambient"]["environment_strength"] <= 2.0
    assert ambient.environment is not None and ambient.environment_strength == drawn["ambient"]["environment_strength"]
    assert {o["mesh"] for o in drawn["objects"]["list"]} == {"tetra.obj"}
    assert all(name.startswith("tetra.obj #") for name in scene.object_names[len(tofcore.demo_scene("room")
                                                                                  .object_names):])


@pytest.mark.parametrize("folder, message", [
    ('library = "nowhere"', r"randomize\.objects\.library: folder not found: .*nowhere"),
    ('library = "empty"', r"randomize\.objects\.library: .*empty holds no mesh files"),
])
def test_missing_or_empty_folders_are_named(tmp_path, folder, message):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SetFileError, match=message):
        load_set(write_set(tmp_path, RANDOM_SET.replace('shapes = ["box", "cylinder", "sphere"]', folder)))


def test_a_dataset_without_randomized_frames_gets_no_pictures(tmp_path):
    from batch.card_figures import diversity_section

    assert diversity_section([{"status": "ok", "valid_fraction": 0.9}], tmp_path) == []
    assert not (tmp_path / "card").exists()
