"""What the command lines share: bounded numbers, --device, --set over Config's fields, the torch
threads, the checks of an output folder, and the machine a result names."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import os
import pathlib
import platform
import tempfile

import torch

from diffstack import Config


def machine() -> str:
    """This machine for a result's provenance: architecture, processor, torch's instruction set,
    cores (the same seed gives the same numbers only on the same: docs/reproducibility.md)."""
    name = platform.processor() or "unknown processor"
    with contextlib.suppress(OSError, StopIteration), open("/proc/cpuinfo") as f:
        name = next(ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name"))
    capability = torch.backends.cpu.get_cpu_capability()
    return f"{platform.machine()}, {name}, {capability}, {os.cpu_count()} cores"


def torch_threads(given: int | None, log=print) -> int:
    """The torch threads of a run, said: --threads, else 2 (two threads that wait on each other run
    slowly where other work keeps a core busy: --threads 1 there)."""
    why = "--threads" if given else "the default"
    log(f"torch threads: {given or 2} ({why}; --threads N to choose)")
    return given or 2


def check_writable(folder, what: str) -> None:
    """Before any work, ValueError naming `what` unless folder can be made and takes files."""
    check_name(folder, what)
    try:
        pathlib.Path(folder).mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-probe-"):
            pass
    except OSError as e:
        raise ValueError(f"{what}: {folder} is not a writable folder ({e.strerror or e})") from None


def check_name(path, what: str) -> None:
    """ValueError naming `what` unless path's name is UTF-8 (files name it in results and logs)."""
    try:
        str(path).encode()
    except UnicodeEncodeError:
        raise ValueError(f"{what}: {os.fsencode(path)!r} is not a UTF-8 name") from None


def bounded(kind, lo, hi, name):
    """An argparse type: a finite `kind` (int or float) in [lo, hi] (lo excluded for floats)."""

    def parse(text):
        try:
            x = kind(text)
        except ValueError:
            what = "a whole number" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"{name} takes {what}, got {text!r}") from None
        if not math.isfinite(x) or x > hi or (x <= lo if kind is float else x < lo):
            bounds = f"> {lo:g} and <= {hi:g}" if kind is float else f"from {lo:,} to {hi:,}"
            raise argparse.ArgumentTypeError(f"{name} must be {bounds}, got {text!r}")
        return x

    return parse


def device_arg(text):
    """An argparse type for --device: a torch device this machine has (cpu, cuda, cuda:N, mps)."""
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        device = None
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if device is None or device.type not in ("cpu", "cuda", "mps"):
        why = "not a torch device the stack runs on (cpu, cuda, cuda:N or mps)"
    elif device.type == "cuda" and count == 0:
        why = "no CUDA device here"
    elif device.type == "cuda" and (device.index or 0) >= count:
        why = f"this machine has {count} CUDA device(s)"
    elif device.type == "mps" and not torch.backends.mps.is_available():
        why = "no MPS device here"
    else:
        return device
    raise argparse.ArgumentTypeError(f"--device {text}: {why}")


# Config fields every data source fixes (2 Hz, 4 s of history, 3 s of future): --set refuses them
SET_BY_DATA = dict(dt=0.5, hist_len=8, horizon=6)


def config_with(cfg: Config, assignments) -> Config:
    """cfg with fields overridden by --set's 'key=value' strings, each parsed to the field's type (a
    tuple: comma-separated numbers); ValueError naming the key otherwise."""
    fields = [f.name for f in dataclasses.fields(Config)]
    changes = {}
    for item in assignments or ():
        key, eq, text = (part.strip() for part in item.partition("="))
        if not eq or key not in fields:
            known = f"unknown Config field {key!r} (known: {', '.join(fields)})"
            raise ValueError(f"--set {item}: {known if eq else 'expected key=value'}")
        default = getattr(cfg, key)
        try:
            if isinstance(default, tuple):  # (every tuple field holds floats)
                value = tuple(float(p) for p in text.strip("()[] ").split(",") if p.strip())
            elif isinstance(default, bool):
                value = {"true": True, "1": True, "false": False, "0": False}[text.lower()]
            else:
                value = type(default)(text)
        except (ValueError, KeyError):
            takes = f"{key} takes a {type(default).__name__} (default {default!r})"
            raise ValueError(f"--set {item}: {takes}, could not parse {text!r}") from None
        if isinstance(value, tuple) and len(value) > 64:
            raise ValueError(f"--set {key}=...: a tuple field takes at most 64 values")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"--set {item}: {key} must be finite")
        if key in SET_BY_DATA and value != SET_BY_DATA[key]:
            raise ValueError(f"--set {item}: {key} is the data's ({SET_BY_DATA[key]:g})")
        changes[key] = value
    return dataclasses.replace(cfg, **changes)


def add_shared_options(ap, **helps) -> None:
    """The options named (jobs, threads, device, overwrite, set), alike in every command line."""
    shared = {
        "jobs": dict(type=bounded(int, 1, 256, "--jobs"), default=None),
        "threads": dict(type=bounded(int, 1, 256, "--threads"), default=None),
        "device": dict(type=device_arg, default="cpu"),
        "overwrite": dict(action="store_true"),
        "set": dict(action="append", default=[], metavar="KEY=VALUE"),
    }
    for name, text in helps.items():
        ap.add_argument(f"--{name}", help=text, **shared[name])
