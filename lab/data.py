"""The data the stack trains on, made or read (load_data), and python -m lab.data: write --scenes
synthetic scenes as a nuScenes v1.0 folder, or read one and summarise it (docs/data.md)."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

import numpy as np
import torch

import data_synth
from data_synth import Dataset, SynthConfig
from lab.cli import add_shared_options, bounded, check_name
from lab.nuscenes import NUSC_VERSIONS, load_nuscenes_cached, load_nuscenes_scenarios
from lab.nuscenes import write_nuscenes
from lab.runs import folder_lock, one_line, refuse_current_folder

MINI_VAL = ("scene-0103", "scene-0916")  # v1.0-mini's official mini_val (the rest: mini_train)


def _scene_names(ranges: str) -> frozenset:
    """'1-2 4' -> {'scene-0001', 'scene-0002', 'scene-0004'}."""
    spans = [(int(p.split("-")[0]), int(p.split("-")[-1])) for p in ranges.split()]
    return frozenset(f"scene-{k:04d}" for lo, hi in spans for k in range(lo, hi + 1))


# The devkit's official v1.0-trainval split (nuscenes/utils/splits.py, v1.2.0: `train`, the union
# of train_detect and train_track, 700 scenes; `val`, 150), as runs of consecutive scene numbers.
NUSC_TRAIN = _scene_names("""
    1-2 4-11 19-34 41-76 120-135 138-139 149-152 154-155 157-168 170-185 187-188 190-196 199-200
    202-204 206-214 218-220 222 224-264 283-306 315-318 321 323-324 328 347-386 388-403 405-408
    410-459 461-465 467-469 471-472 474-480 499-502 504-515 517-518 525-539 541-546 566 568 570-578
    580 582-600 639-679 681 683-689 695-698 700-701 703-719 726-728 730-731 733-741 744 746-747
    749-752 757-765 767-769 786-787 789-792 803-806 808-813 815-817 819-822 847-856 858 860-866
    868-873 875-878 880 882-903 945 947 949 952-953 955-961 975-984 988-992 994-1025 1044-1058
    1074-1102 1104-1110""")
NUSC_VAL = _scene_names("""
    3 12-18 35-36 38-39 92-110 221 268-278 329-332 344-346 519-524 552-565 625-627 629-630 632-638
    770-771 775 777-778 780-784 794-800 802 904-917 919-931 962-963 966-969 971-972 1059-1073""")


def _split_scenes(names: list, version: str) -> tuple:
    """(is_val (S,) bool, rule): v1.0-mini's mini_val scenes; v1.0-trainval the devkit's split (the
    others split by name); fallback (none listed, a side empty): the last 15 % by name."""

    def by_name(idx):
        return set(sorted(idx, key=lambda i: names[i])[-max(1, round(0.15 * len(idx))) :])

    if version == "v1.0-trainval":
        others = [i for i, nm in enumerate(names) if nm not in NUSC_TRAIN and nm not in NUSC_VAL]
        val = {i for i, nm in enumerate(names) if nm in NUSC_VAL}
        val |= by_name(others) if 0 < len(others) < len(names) else set()
        rule = "the official v1.0-trainval val scenes"
        rule += " (+ the last 15 % by name of the others)" if others else ""
    else:
        val = {i for i, nm in enumerate(names) if nm in MINI_VAL}
        rule = "the official v1.0-mini val scenes"
    if not val or len(val) == len(names):  # (no scene listed: none is val)
        val, rule = by_name(list(range(len(names)))), "the last 15 % of the scenes by name"
    return torch.tensor([i in val for i in range(len(names))], dtype=torch.bool), rule


def nuscenes_version(path) -> str:
    """The version a --data folder holds (v1.0-mini, else v1.0-trainval); cheap: checked first."""
    if not Path(path).is_dir():
        raise ValueError(f"--data: {path} is not a folder")
    for version in ("v1.0-mini", "v1.0-trainval"):
        if (Path(path) / version).is_dir():
            return version
    raise ValueError(f"--data: {path} holds no nuScenes version folder (v1.0-mini, v1.0-trainval)")


def load_data(path=None, n=4000, seed=0, cache_dir="data_cache", log=print, workers=None):
    """A Dataset: synthetic samples (n of data seed `seed`), or the nuScenes folder at `path` split
    by scene (the rule logged), cached in cache_dir."""
    data_synth._check_seed("load_data", seed)
    if path is None:
        return _synthetic(n, seed, cache_dir)
    version = nuscenes_version(path)
    scenes, report = load_nuscenes_cached(Path(path), version, None, cache_dir, workers, log)
    if len(scenes) < 2:
        raise ValueError(f"--data: {path} has {len(scenes)} usable scene(s); training needs 2")
    is_val, rule = _split_scenes(scenes.names, version)
    rng = np.random.default_rng(seed)
    train, _ = data_synth.cut_samples(scenes[~is_val], None, rng)
    val, _ = data_synth.cut_samples(scenes[is_val], None, rng)
    counts = {k: v for k, v in report.items() if k != "skipped"}
    skipped = "".join(f"\n  skipped {why}" for why in report.get("skipped", []))
    what = f"{len(train)} training and {len(val)} validation samples (validation: {rule})"
    log(f"read {path} ({version}): {what}; {counts}{skipped}")
    return Dataset(train, val, scenes[is_val])


def _synthetic(n, seed, cache_dir) -> Dataset:
    """load_or_generate, holding cache_dir while a missing cache is made; a cache holding NaN or inf
    (damaged: the generator makes none) is refused, naming it."""
    data_synth._check_count("load_data", "n (samples)", n, data_synth.MAX_SAMPLES)
    made = data_synth._cache_path(int(n), int(seed), SynthConfig(), cache_dir)[0]
    lock = contextlib.nullcontext()
    if not made.exists():
        lock = folder_lock(cache_dir, f"making the data cache {made.name}")
    with lock:
        data = data_synth.load_or_generate(n, seed=seed, cache_dir=cache_dir)
    parts = {p: b.tensors() for p, b in data._asdict().items() if b is not None}
    bad = [f"{p}.{k}" for p, t in parts.items() for k, v in t.items() if not v.isfinite().all()]
    if bad:
        raise ValueError(f"{made}: the data cache holds NaN or inf in {', '.join(bad)}")
    return data


# === the command line ===========================================================================


def main(argv=None) -> None:
    """python -m lab.data {write-nuscenes,read-nuscenes} PATH [options]."""
    ap = argparse.ArgumentParser(prog="python -m lab.data", description=__doc__)
    ap.add_argument("command", choices=("write-nuscenes", "read-nuscenes"))
    ap.add_argument("path", help="the folder to write or read")
    ap.add_argument("--seed", type=bounded(int, 0, 2**63 - 1, "--seed"), default=0)
    ap.add_argument("--scenes", type=bounded(int, 1, data_synth.MAX_SCENES, "--scenes"), default=10)
    ap.add_argument("--version", default="v1.0-mini", choices=NUSC_VERSIONS)
    ap.add_argument("--workers", type=bounded(int, 1, 1024, "--workers"), help="parsing processes")
    ap.add_argument("--cache-dir", help="read-nuscenes: cache the parse there")
    add_shared_options(ap, overwrite="write-nuscenes: replace what is there")
    args = ap.parse_args(argv)
    with one_line(ap):  # bad input (a bad file, a foreign cache, a file in the way): one line
        check_name(args.path, "path")
        if args.command == "write-nuscenes":
            refuse_current_folder(args.path, "write-nuscenes")  # (before any work)
            scenes = data_synth.generate_scenes(args.scenes, seed=args.seed)
            write_nuscenes(scenes, args.path, args.version, overwrite=args.overwrite)
            print(f"wrote {args.scenes} scenes to {args.path}/{args.version} and {args.path}/maps")
            return
        batch, report = load_nuscenes_scenarios(
            args.path, args.version, workers=args.workers, cache_dir=args.cache_dir
        )
        print(data_synth.format_statistics(data_synth.statistics(batch)))
        print("".join(f"skipped {why}\n" for why in report.pop("skipped")), end="")
        print(f"{len(batch)} samples: {report}")


if __name__ == "__main__":
    main()
