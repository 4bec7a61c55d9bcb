"""Bad input to data_synth.py and lab_data.py gets a clear error naming the culprit, raised before
any work where possible.

The nuScenes loader (NaN / Infinity, time steps, sample chains, quaternions, duplicate tokens, map
locations, malformed tables), the memory bounds (lane points, numbers of samples and scenes), the
command line, the official v1.0-trainval split, and a property test: hundreds of randomly corrupted
copies of one small valid folder each end in a load or a clean error that names a file. Every check
is paired with a valid input that passes it."""

import collections
import hashlib
import json
import random
import re
import shutil
import time
import traceback

import numpy as np
import pytest
import torch

from lab import data as lab_data
import data_synth
from lab import nuscenes

FormatError = lab_data.NuScenesFormatError
TABLE_DIR = "v1.0-mini"


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """A valid 3-scene v1.0-mini folder, written once per module (copy it before corrupting it)."""
    root = tmp_path_factory.mktemp("nuscenes") / "valid"
    nuscenes.write_nuscenes(data_synth.generate_scenes(3, seed=1), root)
    return root


@pytest.fixture
def folder(valid, tmp_path):
    dst = tmp_path / "nusc"
    shutil.copytree(valid, dst)
    return dst


def table(root, name):
    return root / TABLE_DIR / f"{name}.json"


def edit(path, fn):
    """Rewrite a JSON file after fn(doc) has edited it in place; returns doc."""
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))  # json.dumps writes NaN / Infinity literally
    return doc


def first_scene_samples(root):
    """The records of sample.json of the first scene, in chain order (as the writer writes them)."""
    samples = json.loads(table(root, "sample").read_text())
    first = json.loads(table(root, "scene").read_text())[0]["first_sample_token"]
    assert samples[0]["token"] == first and samples[0]["prev"] == ""
    return samples


def a_map(root):
    """The map expansion file of the first log, and a lane token of it."""
    loc = json.loads(table(root, "log").read_text())[0]["location"]
    path = root / "maps" / "expansion" / f"{loc}.json"
    return path, json.loads(path.read_text())["lane"][0]["token"]


# --------------------------------------------------------------------------------------------------
# the valid folder loads (so the checks below do not pass because everything errors)


def test_valid_folder_loads(valid):
    scenes, report = lab_data.load_nuscenes(valid)
    assert report["loaded"] == 3 and len(scenes) == 3
    assert all(torch.isfinite(v).all() for v in scenes.tensors().values() if v.is_floating_point())


# --------------------------------------------------------------------------------------------------
# 1. the nuScenes loader


@pytest.mark.parametrize(
    "bad", [float("nan"), float("inf"), float("-inf")], ids=["NaN", "Infinity", "-Infinity"]
)
@pytest.mark.parametrize(
    "name, index, field, k",
    [
        # record 0: a CAM_FRONT pose (the writer alternates CAM_FRONT, LIDAR_TOP)
        ("ego_pose", 0, "translation", 0),
        ("ego_pose", 2, "rotation", 3),
        ("sample_annotation", 0, "translation", 1),
        ("sample_annotation", 5, "size", 2),
        ("sample_annotation", 7, "rotation", 0),
        ("sample", 3, "timestamp", None),
    ],
)
def test_non_finite_numbers_name_file_field_and_token(folder, name, index, field, k, bad):
    def put(doc):
        if k is None:
            doc[index][field] = bad
        else:
            doc[index][field][k] = bad

    doc = edit(table(folder, name), put)
    # the literal is on disk
    assert ("NaN" if bad != bad else "Infinity") in table(folder, name).read_text()
    with pytest.raises(
        FormatError, match=rf"{name}\.json: {field} of (sample )?'{doc[index]['token']}'"
    ):
        lab_data.load_nuscenes(folder)


def test_non_finite_numbers_in_the_map_name_the_lane(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["arcline_path_3"][lane][0].update(radius=float("nan")))
    with pytest.raises(
        FormatError, match=rf"{path.name}: radius of an arcline path of lane '{lane}'"
    ):
        lab_data.load_nuscenes(folder)
    edit(
        path,
        lambda js: js["arcline_path_3"][lane][0].update(
            radius=10.0, segment_length=[0.0, float("inf"), 0.0]
        ),
    )
    with pytest.raises(
        FormatError, match=rf"{path.name}: segment_length of an arcline path of lane '{lane}'"
    ):
        lab_data.load_nuscenes(folder)


def test_numbers_in_fields_the_loader_does_not_read_are_left_alone(folder):
    edit(
        table(folder, "calibrated_sensor"),
        lambda d: d[0]["camera_intrinsic"][0].__setitem__(0, float("nan")),
    )
    # a LIDAR_TOP pose
    edit(table(folder, "ego_pose"), lambda d: d[1]["translation"].__setitem__(0, float("nan")))
    assert lab_data.load_nuscenes(folder)[1]["loaded"] == 3


@pytest.mark.parametrize("step", [0, -500_000], ids=["zero", "negative"])
def test_time_step_between_samples_must_be_positive(folder, step):
    samples = first_scene_samples(folder)
    samples[5]["timestamp"] = samples[4]["timestamp"] + step
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: timestamp of sample '{samples[5]['token']}' .* must be > 0",
    ):
        lab_data.load_nuscenes(folder)


@pytest.mark.parametrize("back_to", [0, 17, 40], ids=["to-first", "to-middle", "to-itself"])
def test_cyclic_sample_chain(folder, back_to):
    samples = first_scene_samples(folder)
    samples[40]["next"] = samples[back_to]["token"]  # the last sample of scene 0 links back
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: the next links of scene 'scene-0061' loop: sample "
        rf"'{samples[40]['token']}' links back to '{samples[back_to]['token']}'",
    ):
        lab_data.load_nuscenes(folder)


def test_broken_prev_link_and_dangling_next(folder):
    samples = first_scene_samples(folder)
    samples[6]["prev"] = samples[3]["token"]
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: sample '{samples[6]['token']}' of scene 'scene-0061' has "
        rf"prev '{samples[3]['token']}' but follows '{samples[5]['token']}'",
    ):
        lab_data.load_nuscenes(folder)
    samples[6]["prev"], samples[6]["next"] = samples[5]["token"], "f" * 32
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: sample '{samples[6]['token']}' .* links next to 'f{{32}}'",
    ):
        lab_data.load_nuscenes(folder)


def test_sample_annotation_chains_are_not_followed(folder):
    # the loader groups annotations by sample and instance; a cyclic prev/next chain among them
    # cannot hang it
    anns = edit(table(folder, "sample_annotation"), lambda d: d[3].update(next=d[0]["token"]))
    assert anns[3]["next"] == anns[0]["token"]
    assert lab_data.load_nuscenes(folder)[1]["loaded"] == 3


def test_one_instance_annotated_twice_in_a_sample(folder):
    def twin(d):
        d.append({**d[0], "token": "e" * 32})

    edit(table(folder, "sample_annotation"), twin)
    with pytest.raises(
        FormatError, match=r"sample_annotation\.json: instance '.*' is annotated twice in sample"
    ):
        lab_data.load_nuscenes(folder)


@pytest.mark.parametrize("name, index", [("ego_pose", 4), ("sample_annotation", 9)])
@pytest.mark.parametrize(
    "q, ok",
    [
        ([0, 0, 0, 0], False),
        ([2.0, 0, 0, 0], False),
        ([1.002, 0, 0, 0], False),
        ([1.0005, 0, 0, 0], True),
    ],
    ids=["zero", "norm2", "off-by-2e-3", "within-tol"],
)
def test_quaternion_norm(folder, name, index, q, ok):
    doc = edit(table(folder, name), lambda d: d[index].update(rotation=q))
    if ok:
        assert lab_data.load_nuscenes(folder)[1]["loaded"] == 3
    else:
        with pytest.raises(
            FormatError,
            match=rf"{name}\.json: rotation of '{doc[index]['token']}' is not a unit "
            rf"quaternion \(norm",
        ):
            lab_data.load_nuscenes(folder)


@pytest.mark.parametrize("name", nuscenes.NUSC_TABLES)
def test_duplicate_tokens(folder, name):
    doc = edit(table(folder, name), lambda d: d.append(dict(d[-1])))
    with pytest.raises(
        FormatError,
        match=rf"{name}\.json: token '{doc[-1]['token']}' appears twice \(records "
        rf"{len(doc) - 2} and {len(doc) - 1}\)",
    ):
        lab_data.load_nuscenes(folder)


def test_duplicate_lane_tokens_in_the_map(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["lane"].append(dict(js["lane"][0])))
    with pytest.raises(
        FormatError, match=rf"{path.name}: lane / lane_connector token '{lane}' appears twice"
    ):
        lab_data.load_nuscenes(folder)


@pytest.mark.parametrize("location", ["../../x", "/etc/passwd", "a/b", "..", "a\\b", "", 7, None])
def test_log_location_must_be_a_plain_map_name(folder, location):
    # a target outside the folder exists
    (folder.parent / "x.json").write_text(json.dumps({"version": "1.3"}))
    doc = edit(table(folder, "log"), lambda d: d[1].update(location=location))
    with pytest.raises(
        FormatError,
        match=rf"log\.json: location {re.escape(repr(location))} of log "
        rf"'{doc[1]['token']}' is not a plain map name",
    ):
        lab_data.load_nuscenes(folder)


def test_log_location_of_a_map_that_is_not_there(folder):
    edit(table(folder, "log"), lambda d: d[0].update(location="atlantis"))
    with pytest.raises(FormatError, match=r"expansion/atlantis\.json: missing"):
        lab_data.load_nuscenes(folder)


# one test per class of malformed table: (file, how to break it, what the message must name)
MALFORMED = {
    "missing table": ("sample_data", lambda p: p.unlink(), r"sample_data\.json: missing"),
    "cut short": (
        "instance",
        lambda p: p.write_text(p.read_text()[:200]),
        r"instance\.json: malformed JSON",
    ),
    "not a list": (
        "scene",
        lambda p: p.write_text('{"token": "x"}'),
        r"scene\.json: a table must be a JSON list",
    ),
    "record not an object": (
        "log",
        lambda p: edit(p, lambda d: d.__setitem__(0, "log")),
        r"log\.json: record 0 is not an object",
    ),
    "record without token": (
        "sensor",
        lambda p: edit(p, lambda d: d[1].pop("token")),
        r"sensor\.json: record 1 is not an object with a string token",
    ),
    "missing key": (
        "sample",
        lambda p: edit(p, lambda d: d[2].pop("next")),
        r"sample\.json: unexpected content "
        r"\(KeyError: 'next'\)",
    ),
    "unknown token": (
        "sample_data",
        lambda p: edit(p, lambda d: d[0].update(ego_pose_token="0" * 32)),
        r"sample_data\.json: unexpected content \(KeyError: '0{32}'\)",
    ),
    "string in a numeric field": (
        "ego_pose",
        lambda p: edit(p, lambda d: d[0]["translation"].__setitem__(1, "12.5")),
        r"ego_pose\.json: translation of '.*' must be 3 finite numbers, got \[.*'12\.5'",
    ),
    "null in a numeric field": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0].update(size=[1.9, None, 1.6])),
        r"sample_annotation\.json: size of '.*' must be 3 finite numbers, got \[1\.9, None",
    ),
    "bool in a numeric field": (
        "sample",
        lambda p: edit(p, lambda d: d[0].update(timestamp=True)),
        r"sample\.json: timestamp of '.*' must be a finite number",
    ),
    "wrong length": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0].update(rotation=[1, 0, 0])),
        r"sample_annotation\.json: rotation of '.*' must be 4 finite numbers",
    ),
    "wrong type of a table": (
        "category",
        lambda p: edit(p, lambda d: d[0].update(name=5)),
        r"category\.json: name of '.*' must be a string, got 5",
    ),
    "dangling first sample": (
        "scene",
        lambda p: edit(p, lambda d: d[0].update(first_sample_token="a" * 32)),
        r"scene\.json: first_sample_token 'a{32}' of scene 'scene-0061' is not a token",
    ),
    "map not an object": (
        "maps",
        lambda p: a_map(p.parent)[0].write_text("[]"),
        r"\.json: a map expansion must be a JSON object",
    ),
    "map shape unknown": (
        "maps",
        lambda p: edit(
            a_map(p.parent)[0],
            lambda js: js["arcline_path_3"][js["lane"][0]["token"]][0].update(shape="XYZ"),
        ),
        r"\.json: shape of an arcline path of lane '.*' must be one of",
    ),
    "map negative length": (
        "maps",
        lambda p: edit(
            a_map(p.parent)[0],
            lambda js: js["arcline_path_3"][js["lane"][0]["token"]][0].update(
                segment_length=[0, -5.0, 0]
            ),
        ),
        r"\.json: segment_length of an arcline path of lane '.*' must be >= 0",
    ),
    "a position no map holds": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0]["translation"].__setitem__(0, 1e30)),
        r"sample_annotation\.json: translation of '.*' is \[1e\+30, .*beyond \+-1e\+06",
    ),
    "a speed no road user reaches": (
        "sample_annotation",
        lambda p: edit(
            p, lambda d: d[0]["translation"].__setitem__(0, d[0]["translation"][0] + 500.0)
        ),
        r"sample_annotation\.json: translation of instance '.*' at sample '.*' of scene "
        r"'.*' puts it at \S+ m/s: no road user",
    ),
    "timestamps in milliseconds": (
        "sample",
        lambda p: edit(p, lambda d: [r.update(timestamp=r["timestamp"] // 1000) for r in d]),
        r"sample\.json: the samples of scene '.*' are 0\.0005 s apart .* 2 Hz",
    ),
    "prediction split not an object": (
        "prediction",
        lambda p: (p.parent / "maps" / "prediction" / "prediction_scenes.json").write_text(
            "[1, 2]"
        ),
        r"prediction_scenes\.json: must be a JSON object",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_tables_name_the_file(folder, case):
    name, corrupt, message = MALFORMED[case]
    corrupt(table(folder, name) if name in nuscenes.NUSC_TABLES else folder / name)
    with pytest.raises(FormatError, match=message):
        lab_data.load_nuscenes(folder)


# --------------------------------------------------------------------------------------------------
# 2. memory bounds


def test_lane_longer_than_the_point_limit_names_the_lane(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["arcline_path_3"][lane][0].update(segment_length=[0.0, 1e9, 0.0]))
    t = time.perf_counter()
    with pytest.raises(
        FormatError,
        match=rf"{path.name}: lane '{lane}' is 1e\+09 m long: 500000001 points at 2\.0 m "
        rf"spacing, more than MAX_LANE_POINTS = {data_synth.MAX_LANE_POINTS}",
    ):
        lab_data.load_nuscenes(folder)
    assert time.perf_counter() - t < 5  # refused before allocating, not after


def test_route_longer_than_the_point_limit_names_the_lanes(folder):
    # every lane 20 km (10 002 points: under the limit), so a route of two or more chained lanes
    # is over it
    path, _ = a_map(folder)
    edit(
        path,
        lambda js: [
            a.update(segment_length=[0.0, 20_002.0, 0.0])
            for arcs in js["arcline_path_3"].values()
            for a in arcs
        ],
    )
    with pytest.raises(
        FormatError,
        match=rf"{path.name}: the route of scene 'scene-0061' through lanes '\w+' \.\. "
        rf"'\w+' is \d+ m long: \d+ points, more than MAX_LANE_POINTS = 20000",
    ):
        lab_data.load_nuscenes(folder)


def test_discretize_refuses_too_many_points_and_bad_spacing():
    seg = np.zeros((1, 1, 5))
    seg[..., 4] = 100.0
    _, mask = data_synth.discretize(seg, 2.0)  # a valid segment: 51 points
    assert mask.sum() == 51
    seg[..., 4] = 1e9
    with pytest.raises(
        ValueError,
        match=rf"discretize: a polyline of 1e\+09 m needs 500000001 points at 2\.0 m "
        rf"spacing, more than MAX_LANE_POINTS = {data_synth.MAX_LANE_POINTS}",
    ):
        data_synth.discretize(seg, 2.0)
    for spacing in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="discretize: spacing must be a finite number > 0"):
            data_synth.discretize(seg, spacing)
    seg[..., 4] = float("nan")
    with pytest.raises(ValueError, match="discretize: a segment length is not finite"):
        data_synth.discretize(seg, 2.0)


@pytest.mark.parametrize(
    "fn, n, culprit",
    [
        (
            data_synth.make_dataset,
            10**8,
            r"make_dataset: n \(samples\) must be a whole number from 1 to 2,000,000, "
            r"got 100000000",
        ),
        (data_synth.make_dataset, 0, r"make_dataset: n \(samples\) .* got 0"),
        (data_synth.make_dataset, 2.5, r"make_dataset: n \(samples\) .* got 2\.5"),
        (
            data_synth.load_or_generate,
            data_synth.MAX_SAMPLES + 1,
            r"load_or_generate: n \(samples\) .* to 2,000,000, "
            r"got 2000001",
        ),
        (data_synth.load_or_generate, -5, r"load_or_generate: n \(samples\) .* got -5"),
        (
            data_synth.generate_scenes,
            data_synth.MAX_SCENES + 1,
            r"generate_scenes: n \(scenes\) .* to 500,000, "
            r"got 500001",
        ),
        (data_synth.generate_scenes, True, r"generate_scenes: n \(scenes\) .* got True"),
    ],
)
def test_generator_counts_are_bounded(fn, n, culprit, tmp_path):
    kwargs = {"cache_dir": tmp_path} if fn is data_synth.load_or_generate else {}
    t = time.perf_counter()
    with pytest.raises(ValueError, match=culprit):
        fn(n, **kwargs)
    assert time.perf_counter() - t < 1 and not list(tmp_path.iterdir())  # refused before any work


def test_generator_seed_chunk_and_samples_per_scene(tmp_path):
    with pytest.raises(ValueError, match=r"generate_scenes: chunk must be .* got 0"):
        data_synth.generate_scenes(2, chunk=0)  # chunk 0 used to loop forever
    with pytest.raises(ValueError, match=r"make_dataset: seed must be a whole number >= 0, got -1"):
        data_synth.make_dataset(8, seed=-1)
    with pytest.raises(ValueError, match=r"make_dataset: cfg\.samples_per_scene .* got 0"):
        data_synth.make_dataset(8, data_synth.SynthConfig(samples_per_scene=0))
    with pytest.raises(
        ValueError,
        match=r"make_dataset: n = 2,000,000 samples at 1 per scene needs 2,000,000 scenes, "
        r"more than MAX_SCENES = 500,000",
    ):
        data_synth.make_dataset(2_000_000, data_synth.SynthConfig(samples_per_scene=1))
    assert len(data_synth.generate_scenes(1, seed=0)) == 1  # the smallest valid request works


# --------------------------------------------------------------------------------------------------
# 3. the command line


@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["generate", "--n", "-5"], "argument --n: must be from 1 to 2,000,000"),
        (["generate", "--n", "0"], "argument --n: must be from 1"),
        (
            ["generate", "--n", "2000001"],
            "argument --n: must be from 1 to 2,000,000 (samples; MAX_SAMPLES), got 2,000,001",
        ),
        (
            ["generate", "--n", "nan"],
            "argument --n: expected a whole number from 1 to 2,000,000 (samples; MAX_SAMPLES), "
            "got 'nan'",
        ),
        (["generate", "--n", "inf"], "argument --n: expected a whole number"),
        (["generate", "--n", "1e9"], "argument --n: expected a whole number"),
        (["generate", "--seed", "-1"], "argument --seed: must be >= 0, got -1"),
        (
            ["write-nuscenes", "OUT", "--scenes", "0"],
            "argument --scenes: must be from 1 to 500,000",
        ),
        (["write-nuscenes", "OUT", "--scenes", "-3"], "argument --scenes: must be from 1"),
        (
            ["write-nuscenes", "OUT", "--scenes", "500001"],
            "argument --scenes: must be from 1 to 500,000 (MAX_SCENES)",
        ),
        (["render", "OUT", "--n", "0"], "argument --n: must be from 1 to 400 (MAX_RENDER), got 0"),
        (["render", "OUT", "--n=-inf"], "argument --n: expected a whole number"),
        (["stats", "--n", "0"], "argument --n: must be from 1"),
        (["stats", "--seed", "nan"], "argument --seed: expected a whole number >= 0, got 'nan'"),
    ],
)
def test_cli_bad_arguments_exit_2_naming_the_argument(argv, culprit, tmp_path, capsys):
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        lab_data.main(argv)
    assert e.value.code == 2 and culprit in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing was written


def test_cli_bad_folder_exits_2_naming_the_file(folder, capsys):
    edit(table(folder, "ego_pose"), lambda d: d[0]["rotation"].__setitem__(0, float("nan")))
    with pytest.raises(SystemExit) as e:
        lab_data.main(["read-nuscenes", str(folder)])
    assert e.value.code == 2 and "ego_pose.json: rotation of" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        # would replace the folder's files
        lab_data.main(["write-nuscenes", str(folder), "--scenes", "1"])
    assert (
        e.value.code == 2
        and "category.json exists (18 files would be replaced)" in capsys.readouterr().err
    )


def test_cli_valid_folder_reads(valid, capsys):
    lab_data.main(["read-nuscenes", str(valid)])  # returns normally: exit 0
    assert "loaded" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------------
# 4. the official train/val split


def test_official_split_literal():
    train, val = lab_data.NUSC_TRAIN, lab_data.NUSC_VAL
    assert len(train) == 700 and len(val) == 150 and not train & val

    # sha1 of the sorted names of the devkit's lists (nuscenes-devkit 1.2.0,
    # nuscenes/utils/splits.py)
    def digest(names):
        return hashlib.sha1(" ".join(sorted(names)).encode()).hexdigest()

    assert digest(train) == "d7e56861c837c75cca7136407ccb19992993fd3d"
    assert digest(val) == "524f82564ff01212a323a339182cca808ac68fc6"
    assert {"scene-0001", "scene-1110", "scene-0061"} <= train and {
        "scene-0003",
        "scene-1073",
        "scene-0103",
    } <= val
    assert lab_data.MINI_VAL == ("scene-0103", "scene-0916")  # the devkit's mini_val


def test_load_data_uses_the_official_split(tmp_path):
    # written as scene-0061 (train), scene-0103, scene-0553 (val)
    scenes = data_synth.generate_scenes(3, seed=1)
    lines = []
    nuscenes.write_nuscenes(scenes, tmp_path / "tv", "v1.0-trainval")
    d = lab_data.load_data(tmp_path / "tv", log=lines.append)
    assert sorted(d.val_scenes.names) == ["scene-0103", "scene-0553"]
    assert "validation: the official v1.0-trainval val scenes" in lines[-1]
    nuscenes.write_nuscenes(scenes, tmp_path / "mini", "v1.0-mini")
    d = lab_data.load_data(tmp_path / "mini", log=lines.append)
    assert d.val_scenes.names == ["scene-0103"] and "official v1.0-mini val" in lines[-1]
    # names in neither list: the fallback, the last 15 % of the scenes by name (at least one)
    edit(
        tmp_path / "tv" / "v1.0-trainval" / "scene.json",
        lambda d: [r.update(name=f"mine-{k}") for k, r in enumerate(d)],
    )
    d = lab_data.load_data(tmp_path / "tv", log=lines.append)
    assert d.val_scenes.names == ["mine-2"] and "the last 15 % of the scenes by name" in lines[-1]
    with pytest.raises(ValueError, match="load_data: seed must be"):
        lab_data.load_data(tmp_path / "tv", seed=-2)


# --------------------------------------------------------------------------------------------------
# 5. property test: randomly corrupted copies of the valid folder


NUMERIC = {
    "translation",
    "rotation",
    "size",
    "timestamp",
    "start_pose",
    "end_pose",
    "radius",
    "segment_length",
    "nbr_samples",
    "num_lidar_pts",
    "x",
    "y",
}
LINKS = ("prev", "next")


def _json_files(root):
    return sorted(p for p in root.rglob("*.json"))


def _load(path):
    return json.loads(path.read_text())


def _record_lists(doc):
    """The lists of records of a table (itself) or of a map expansion (layers, arcline paths)."""
    if isinstance(doc, list):
        return [doc]
    lists = [v for k, v in doc.items() if isinstance(v, list) and v and isinstance(v[0], dict)]
    lists += [arcs for arcs in doc.get("arcline_path_3", {}).values()]
    return [x for x in lists if x]


def _pick_record(rng, root, keys=None, files=None):
    """(path, doc, record): a random record of a random file with one of `keys` (any if None)."""
    files = files or [p for p in _json_files(root) if "prediction" not in p.parts]
    for _ in range(100):
        path = rng.choice(files)
        doc = _load(path)
        lists = _record_lists(doc)
        if not lists:
            continue
        recs = rng.choice(lists)
        rec = rng.choice(recs)
        if isinstance(rec, dict) and (keys is None or any(k in rec for k in keys)):
            return path, doc, recs, rec
    raise AssertionError("no record found")


def _tables(root, *names):
    return [table(root, n) for n in names]


def c_drop_file(rng, root):
    path = rng.choice(_json_files(root))
    path.unlink()
    return f"delete {path.name}"


def c_cut_short(rng, root):
    path = rng.choice(_json_files(root))
    text = path.read_text()
    cut = rng.randrange(len(text))
    path.write_text(text[:cut])
    return f"cut {path.name} at {cut}/{len(text)}"


def c_replace_token(rng, root):
    path, doc, recs, rec = _pick_record(rng, root)
    keys = [
        k
        for k, v in rec.items()
        if k == "token" or k.endswith("_token") or k in LINKS or k.endswith("_tokens")
    ]
    if not keys:
        return "no token field"
    key = rng.choice(keys)
    other = rng.choice(recs).get("token", "")
    new = rng.choice(["%032x" % rng.getrandbits(128), other, "", "1"])
    rec[key] = [new] if isinstance(rec[key], list) else new
    path.write_text(json.dumps(doc))
    return f"{path.name}: {key} -> {new!r}"


def _numeric_key(rng, rec):
    keys = [k for k in rec if k in NUMERIC]
    return rng.choice(keys) if keys else None


def _put(rng, rec, key, value):
    if isinstance(rec[key], list) and rec[key] and rng.random() < 0.8:
        rec[key][rng.randrange(len(rec[key]))] = value
    else:
        rec[key] = value


def c_nan_inf(rng, root):
    path, doc, _, rec = _pick_record(rng, root, NUMERIC)
    key = _numeric_key(rng, rec)
    value = rng.choice([float("nan"), float("inf"), float("-inf")])
    _put(rng, rec, key, value)
    path.write_text(json.dumps(doc))
    return f"{path.name}: {key} <- {value}"


def c_wrong_type(rng, root):
    path, doc, _, rec = _pick_record(rng, root, NUMERIC)
    key = _numeric_key(rng, rec)
    value = rng.choice(["abc", "1.5", None, True, [], {}, [1, 2]])
    _put(rng, rec, key, value)
    path.write_text(json.dumps(doc))
    return f"{path.name}: {key} <- {value!r}"


def c_delete_key(rng, root):
    path, doc, _, rec = _pick_record(rng, root)
    key = rng.choice(sorted(rec))
    del rec[key]
    path.write_text(json.dumps(doc))
    return f"{path.name}: del {key}"


def c_duplicate_record(rng, root):
    path, doc, recs, rec = _pick_record(rng, root)
    recs.insert(rng.randrange(len(recs) + 1), dict(rec))
    path.write_text(json.dumps(doc))
    return f"{path.name}: duplicate {rec.get('token', '?')}"


def c_bad_quaternion(rng, root):
    path, doc, _, rec = _pick_record(
        rng, root, ["rotation"], _tables(root, "ego_pose", "sample_annotation", "calibrated_sensor")
    )
    q = rng.choice(
        [[0, 0, 0, 0], [q * 2 for q in rec["rotation"]], rec["rotation"][:3], [0.0, 0.0, 0.0, 1e-9]]
    )
    rec["rotation"] = q
    path.write_text(json.dumps(doc))
    return f"{path.name}: rotation <- {q}"


def c_break_link(rng, root):
    path, doc, recs, rec = _pick_record(
        rng, root, LINKS, _tables(root, "sample", "sample_annotation", "sample_data")
    )
    key = rng.choice(LINKS)
    new = rng.choice(
        [
            rec["token"],
            rng.choice(recs)["token"],
            recs[0]["token"],
            "",
            "%032x" % rng.getrandbits(128),
        ]
    )
    rec[key] = new
    path.write_text(json.dumps(doc))
    return f"{path.name}: {key} -> {new!r}"


def c_wrong_container(rng, root):
    path = rng.choice(_json_files(root))
    doc = _load(path)
    lists = _record_lists(doc)
    if rng.random() < 0.3 or not lists:
        doc = rng.choice([{}, [], "x", 3, None, {"token": "x"}])
    else:
        recs = rng.choice(lists)
        recs[rng.randrange(len(recs))] = rng.choice(["x", 3, None, [], [1, 2]])
    path.write_text(json.dumps(doc))
    return f"{path.name}: container"


def c_bad_location(rng, root):
    path = table(root, "log")
    doc = _load(path)
    new = rng.choice(
        ["../../x", "/etc/passwd", "a/b", "..", "", "nowhere", 7, None, ["x"], "boston-seaport"]
    )
    rng.choice(doc)["location"] = new
    path.write_text(json.dumps(doc))
    return f"log.json: location <- {new!r}"


def c_map_geometry(rng, root):
    files = [p for p in (root / "maps" / "expansion").glob("*.json") if _load(p)["lane"]]
    path = rng.choice(files)
    doc = _load(path)
    arc = rng.choice(rng.choice(list(doc["arcline_path_3"].values())))
    key, value = rng.choice(
        [
            ("radius", -1.0),
            ("radius", 0.0),
            ("segment_length", [0.0, 1e9, 0.0]),
            ("segment_length", [0.0, -3.0, 0.0]),
            ("shape", "XYZ"),
            ("shape", 5),
            ("start_pose", [1.0, 2.0]),
            ("radius", float("nan")),
        ]
    )
    arc[key] = value
    path.write_text(json.dumps(doc))
    return f"{path.name}: {key} <- {value!r}"


CORRUPTIONS = [
    c_drop_file,
    c_cut_short,
    c_replace_token,
    c_nan_inf,
    c_wrong_type,
    c_delete_key,
    c_duplicate_record,
    c_bad_quaternion,
    c_break_link,
    c_wrong_container,
    c_bad_location,
    c_map_geometry,
]
N_CASES = 300


@pytest.mark.slow
def test_random_corruptions_load_or_fail_cleanly(valid, tmp_path):
    rng = random.Random(20260)
    outcomes = {c.__name__[2:]: collections.Counter() for c in CORRUPTIONS}
    failures = []
    t0 = time.perf_counter()
    for i in range(N_CASES):
        corrupt = CORRUPTIONS[i % len(CORRUPTIONS)]
        root = tmp_path / f"case{i}"
        shutil.copytree(valid, root)
        what = corrupt(rng, root)
        try:
            scenes, _ = lab_data.load_nuscenes(root)
        except (ValueError, FileNotFoundError) as e:
            outcome = type(e).__name__
            if not str(e).startswith(str(root)) or not re.search(
                r"\.json|v1\.0-mini", str(e).split(":")[0]
            ):
                failures.append(
                    f"case {i} ({corrupt.__name__}: {what}): {outcome} does not name a file: {e}"
                )
        except BaseException as e:  # anything else is a bug of the loader
            outcome = type(e).__name__
            failures.append(
                f"case {i} ({corrupt.__name__}: {what}): {outcome}: "
                f"{traceback.format_exc(limit=-3)}"
            )
        else:
            outcome = "loaded"
            if not all(
                torch.isfinite(v).all() for v in scenes.tensors().values() if v.is_floating_point()
            ):
                failures.append(
                    f"case {i} ({corrupt.__name__}: {what}): loaded with a non-finite value"
                )
        outcomes[corrupt.__name__[2:]][outcome] += 1
        shutil.rmtree(root)
    seconds = time.perf_counter() - t0
    print(f"\n{N_CASES} corrupted folders in {seconds:.1f} s; outcome per class of corruption:")
    for name, counts in outcomes.items():
        print(f"  {name:18s} {dict(sorted(counts.items()))}")
    assert not failures, "\n".join(failures)
    assert all(sum(c.values()) >= 1 for c in outcomes.values())  # every class was exercised
    total = sum(outcomes.values(), collections.Counter())
    assert total["loaded"] > 0 and total["NuScenesFormatError"] > N_CASES / 2  # both ends happen


# --------------------------------------------------------------------------------------------------
# fuzz: seeded random mutations of a folder and of the resume store
# --------------------------------------------------------------------------------------------------

MUTANTS = (
    None,
    True,
    "x",
    -1,
    0,
    1e30,
    -1e30,
    float("nan"),
    float("inf"),
    [],
    {},
    [1, 2],
    "0" * 32,
)


@pytest.mark.slow
def test_random_mutations_of_a_folder_are_read_or_refused_by_name(valid, tmp_path):
    """300 seeded mutations, each a random field (a numeric one more often than not) of a random
    record of a random table set to a value of another kind or out of range: the reader either reads
    the folder or refuses it with a NuScenesFormatError naming the file, never another exception
    (a traceback), and never returns a non-finite number."""
    rng = random.Random(0)
    names = (
        "sample",
        "sample_annotation",
        "ego_pose",
        "instance",
        "scene",
        "log",
        "category",
        "sample_data",
    )
    for trial in range(300):
        root = tmp_path / f"t{trial}"
        shutil.copytree(valid, root)
        name = rng.choice(names)
        path = table(root, name)
        doc = json.loads(path.read_text())
        rec = rng.choice(doc)

        def number(x):
            return isinstance(x, (int, float)) and not isinstance(x, bool)

        numeric = sorted(
            k
            for k, v in rec.items()
            if number(v) or isinstance(v, list) and v and all(map(number, v))
        )
        key = rng.choice(numeric) if numeric and rng.random() < 0.6 else rng.choice(sorted(rec))
        if isinstance(rec[key], list) and rec[key] and rng.random() < 0.7:
            # one element of a vector
            rec[key][rng.randrange(len(rec[key]))] = rng.choice(MUTANTS)
        else:
            rec[key] = rng.choice(MUTANTS)
        path.write_text(json.dumps(doc))
        try:
            scenes, _ = lab_data.load_nuscenes(root)
        except FormatError as e:
            assert f"{name}.json" in str(e) or "json" in str(e), (trial, name, key, str(e))
        else:
            for k, v in scenes.tensors().items():
                assert not v.is_floating_point() or torch.isfinite(v).all(), (trial, name, key, k)
        shutil.rmtree(root)


def test_random_corruption_of_resume_pieces_is_named_and_recomputed(tmp_path, capsys):
    """Seeded random truncations and byte flips of finished pieces: the store never raises, and a
    piece it still calls finished loads."""
    from lab import runs
    from lab import tables as lt

    rng = random.Random(1)
    store = runs.RunStore(tmp_path, "k")
    pieces = [lt.Piece("Standard", s, None) for s in range(30)]
    for p in pieces:
        store.save("rl", p, {"ade": 1.0 + p.seed, "curve": [1.0, 2.0]})
    for p in pieces:
        raw = bytearray(store.path("rl", p).read_bytes())
        if rng.random() < 0.5:
            raw = raw[: rng.randrange(len(raw))]
        else:
            for _ in range(rng.randrange(1, 4)):
                raw[rng.randrange(len(raw))] = rng.randrange(256)
        store.path("rl", p).write_bytes(bytes(raw))
        if store.has("rl", p):
            result, _ = store.load("rl", p)
            assert isinstance(result, dict)
        else:
            assert store.path("rl", p).with_suffix(".corrupt").exists()
    assert "not a finished piece" in capsys.readouterr().err


def test_a_nan_inside_the_data_cache_is_refused_naming_the_cache(tmp_path):
    lab_data.load_data(n=40, seed=3, cache_dir=tmp_path)  # makes the cache
    (path,) = tmp_path.glob("scenarios-n40-s3-*.pt")
    blob = torch.load(path, weights_only=True)
    blob["train"]["agent_hist"][0, 0, 0] = float("nan")
    torch.save(blob, path)
    with pytest.raises(
        ValueError,
        match=rf"{re.escape(str(path))}: the data cache holds NaN or inf in train\.agent_hist",
    ):
        lab_data.load_data(n=40, seed=3, cache_dir=tmp_path)


def test_a_data_cache_being_made_by_another_process_is_refused_naming_it(tmp_path):
    """While one process makes a data cache, another asking for the same missing cache is told who
    makes it."""
    import subprocess
    import sys

    from lab import runs

    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom lab import runs\n"
            "with runs.folder_lock(sys.argv[1], 'making the data cache'):\n"
            " print('held', flush=True); time.sleep(60)",
            str(tmp_path),
        ],
        cwd=runs.ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(
            ValueError,
            match=rf"{re.escape(str(tmp_path))}: another run is writing here \(PID {holder.pid}",
        ):
            lab_data.load_data(n=40, seed=4, cache_dir=tmp_path)
    finally:
        holder.kill()
        holder.wait()
    # the holder gone: made here
    assert len(lab_data.load_data(n=40, seed=4, cache_dir=tmp_path).train) > 0


def test_render_never_replaces_a_file_and_names_the_png_it_writes(tmp_path, capsys, monkeypatch):
    from lab import data as lab_data

    kept = tmp_path / "learning_curves.png"
    kept.write_bytes(b"a committed figure")
    with pytest.raises(SystemExit) as e:
        lab_data.main(["render", str(kept), "--n", "1"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and f"{kept} exists" in err and "--overwrite" in err
    assert kept.read_bytes() == b"a committed figure"
    lab_data.main(["render", str(tmp_path / "grid"), "--n", "1"])
    out = capsys.readouterr().out
    assert (tmp_path / "grid.png").exists() and not (tmp_path / "grid").exists()
    assert f"to {tmp_path / 'grid.png'}" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid.png", "learning_curves.png"]
    lab_data.main(["render", str(kept), "--n", "1", "--overwrite"])
    assert kept.read_bytes()[:4] == b"\x89PNG"
