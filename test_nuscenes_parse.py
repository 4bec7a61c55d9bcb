"""Reading nuScenes folders at scale (lab_data.py section 1): the scenes parsed by a process pool,
and the parse cached keyed by the sha256 of the folder's files."""

import json
import shutil

import pytest
import torch

from lab import data as lab_data
import data_synth
from lab import nuscenes


def _files(folder):
    """The names in `folder` but its .lock (the record of who holds it: runs.folder_lock)."""
    return [p.name for p in folder.iterdir() if p.name != ".lock"]


SCENES = 40  # 3 chunks of PARSE_CHUNK = 16: a pool of 2 workers gets more than one task each


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("nusc") / "nusc"
    nuscenes.write_nuscenes(data_synth.generate_scenes(SCENES, seed=5), root)
    return root


def same(a: data_synth.Scenes, b: data_synth.Scenes) -> bool:
    return (
        a.names == b.names
        and a.tensors().keys() == b.tensors().keys()
        and all(torch.equal(v, b.tensors()[k]) for k, v in a.tensors().items())
    )


def test_the_pool_gives_the_scenes_of_one_process(folder):
    assert lab_data.PARSE_CHUNK * 2 < SCENES  # the pool really runs with 2 workers
    one, report1 = lab_data.load_nuscenes(folder, workers=1)
    two, report2 = lab_data.load_nuscenes(folder, workers=2)
    assert report1 == report2 and report1["loaded"] == SCENES
    assert same(one, two)


def test_workers_must_be_a_whole_number(folder):
    with pytest.raises(ValueError, match="workers must be a whole number >= 1, got 0"):
        lab_data.load_nuscenes(folder, workers=0)


def test_a_cache_hit_gives_the_fresh_parse(folder, tmp_path):
    lines = []
    fresh, report = lab_data.load_nuscenes(folder, workers=1)
    first, _ = lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path, log=lines.append)
    assert "parsed in" in lines[-1]
    second, report2 = lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path, log=lines.append)
    assert "read from the cache" in lines[-1]
    assert report2 == report and same(fresh, first) and same(fresh, second)
    assert _files(tmp_path) == [lab_data.nuscenes_cache_path(folder, "v1.0-mini", tmp_path).name]


@pytest.mark.slow
def test_a_second_parse_into_a_cache_being_written_is_refused(
    folder, tmp_path, lock_held_elsewhere
):
    from lab import runs

    # another process holds the cache folder (this one may hold it again: runs.folder_lock)
    with lock_held_elsewhere(tmp_path, "another parse"):
        with pytest.raises(
            runs.OutputRefused, match=r"another run is writing here .*`another parse`"
        ):
            lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path)
    assert not list(tmp_path.glob("*.pt"))
    # once the first has ended, it goes ahead
    lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.pt"))) == 1


@pytest.mark.slow
def test_a_changed_table_invalidates_the_cache(folder, tmp_path):
    changed = tmp_path / "changed"
    shutil.copytree(folder, changed)
    cache = tmp_path / "cache"
    lines = []
    before, _ = lab_data.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    table = changed / "v1.0-mini" / "sample_annotation.json"
    anns = json.loads(table.read_text())
    anns[0]["translation"][0] += 0.5  # one box 0.5 m further
    table.write_text(json.dumps(anns))
    after, _ = lab_data.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    assert "out of date (v1.0-mini/sample_annotation.json changed); parsing again" in lines[-2]
    assert not same(before, after) and same(after, lab_data.load_nuscenes(changed, workers=1)[0])
    # and the replaced cache now holds the new parse
    again, _ = lab_data.load_nuscenes_cached(changed, cache_dir=cache, log=lines.append)
    assert "read from the cache" in lines[-1] and same(after, again)
    assert len(_files(cache)) == 1  # one cache per folder, replaced (no temporary file left)


def test_a_foreign_file_under_the_cache_name_is_refused_and_kept(folder, tmp_path):
    path = lab_data.nuscenes_cache_path(folder, "v1.0-mini", tmp_path)
    path.write_text("my notes")
    with pytest.raises(ValueError, match="not a readable data_synth nuScenes cache"):
        lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path, log=lambda s: None)
    assert path.read_text() == "my notes"


def test_a_failed_cache_write_leaves_nothing(folder, tmp_path, monkeypatch):
    def full_disk(obj, f):
        open(f, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(data_synth.torch, "save", full_disk)
    with pytest.raises(OSError, match="No space left"):
        lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path, log=lambda s: None)
    assert _files(tmp_path) == []


def test_load_data_parses_once_then_reads_the_cache(folder, tmp_path):
    lines = []
    a = lab_data.load_data(folder, cache_dir=tmp_path, log=lines.append)
    b = lab_data.load_data(folder, cache_dir=tmp_path, log=lines.append)
    assert any("parsed in" in s for s in lines[:2]) and any(
        "read from the cache" in s for s in lines[2:]
    )
    assert all(torch.equal(v, b.train.tensors()[k]) for k, v in a.train.tensors().items())


def test_a_cache_of_an_earlier_version_is_parsed_again(folder, tmp_path):
    import torch

    path = lab_data.nuscenes_cache_path(folder, "v1.0-mini", tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"key": '{"version": "v1.0-mini", "sums": {}}', "scenes": {}}, path)  # other keys
    lines = []
    scenes, _ = lab_data.load_nuscenes_cached(folder, cache_dir=tmp_path, log=lines.append)
    assert len(scenes.ego) == SCENES
    assert any("an earlier version of the project wrote it" in s for s in lines)
