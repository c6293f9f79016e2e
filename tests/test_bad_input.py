"""The command line never shows a traceback for bad input: every command, every file it reads or writes, fed
malformed files and paths, answers with one line naming the problem and exit code 2 (issue 16, "Done when").

The sweep is a table: :data:`COMMANDS` gives each command's arguments with a ``{slot}`` for every file or folder it
takes, and :data:`SLOTS` says what kind of input each slot is; :data:`BAD` gives every kind its malformed variants. A
new command is one line in :data:`COMMANDS` (and a new kind of file one entry in :data:`BAD`). Every case runs through
the real entry point, :func:`efficienttrack.cli.main`, in-process; each one stops before any work.
"""

from __future__ import annotations

import dataclasses
import errno
import inspect
import json
import math
import os
import re
import shutil
import sys
import tempfile
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from efficienttrack import cli
from efficienttrack.core.errors import EfficientTrackError
from efficienttrack.core.fileio import atomic_write, output_lock
from efficienttrack.data.metrics import compute_metrics
from efficienttrack.data.records import save_records
from efficienttrack.data.references import Reference, save_references
from efficienttrack.learn import checkpoints
from efficienttrack.learn.checkpoints import load_tensors
from efficienttrack.learn.dynamics import save_model, train_model
from efficienttrack.learn.policy import save_policy, train_policy
from efficienttrack.learn.settings import MODEL_PRESETS, POLICY_PRESETS
from efficienttrack.systems.hydraulic import preset_path
from efficienttrack.systems.limits import GuardLimits
from efficienttrack.systems.pd import PD_PRESETS
from efficienttrack.systems.protocol import BatchedSystem
from efficienttrack.workflow.collect import CollectConfig, collect
from test_cli import click_command
from test_records import make_record
from test_rosbag import references, states, write_bag
from toy_system import LagSystem, sine_refs

COMMANDS: dict[str, str] = {
    "refs generate": "refs generate --out {out_folder} --n 2",
    "refs plot": "refs plot {refs} --out {out_png}",
    "metrics": "metrics {records} --csv {out_csv}",
    "convert": "convert {records} --out {out_folder}",
    "collect": "collect --refs {refs} --out {out_folder} --plant xe75 --pd {pd} --passes 1",
    "evaluate": "evaluate --refs {refs} --out {out_folder} --plant xe75 --pd {pd} --limits {limits} --policy {policy} "
    "--device cpu --plots 0",
    "run": "run --train-refs {refs} --test-refs {refs2} --out {out_folder} --limits {limits} --config {config} "
    "--preset tiny --device cpu --plots 0",
    "demo": "demo --out {out_folder} --config {config} --preset tiny --device cpu --plots 0",
    "train-model": "train-model --data {records} --held-out {records2} --init-model {model} --out {out_pt} "
    "--preset tiny --steps 2 --device cpu",
    "model-error": "model-error --model {model} --data {records} --steps 2 --device cpu",
    "train-policy": "train-policy --model {model} --data {records} --held-out {records2} --init-policy {policy} "
    "--out {out_pt} --preset tiny --steps 2 --device cpu",
    "round": "round --model {model} --policy {policy} --data {records} --old-data {records2} --held-out {records3} "
    "--out {out_folder} --preset tiny --steps-model 2 --steps-policy 2 --device cpu",
    "sim calibrate": "sim calibrate --logs {records} --start {params} --out {out_json} --max-windows 2 --max-nfev 2",
    "sim fidelity": "sim fidelity --logs {records} --plant xe75 --pd {pd} --system-opt params_file={params} "
    "--plot {out_folder}",
    "export": "export --policy {policy} --out {out_folder}",
    "import-rosbag": "import-rosbag {bag} --reference /cmd --out {out_folder}",
    "deploy": "deploy --refs {refs} --out {out_folder} --policy {policy} --limits {limits} --arm --shadow --fast "
    "--plant xe75 --pd {pd} --device cpu",
    "limits": "limits --from-logs {records} --out {out_json}",
    "study": "study --train-refs {refs} --test-refs {refs2} --out {out_folder} --limits {limits} --preset tiny "
    "--methods pd --budget 10",
    "ablate": "ablate history --train-refs {refs} --test-refs {refs2} --out {out_folder} --preset tiny --values 1 --passes 1",
    "config show": "config show tiny --config {config}",
    "study-plot": "study-plot {study} --out {out_png}",
}
"""Each command's arguments, a ``{slot}`` for every file or folder (a slot's kind: :data:`SLOTS`)."""

SLOTS: dict[str, str] = {
    "refs": "refs",
    "refs2": "refs",
    "records": "records",
    "records2": "records",
    "records3": "records",
    "model": "model",
    "policy": "policy",
    "config": "config",
    "pd": "pd",
    "limits": "limits",
    "params": "params",
    "bag": "bag",
    "study": "study",
    "out_folder": "out_folder",
    "out_pt": "out_checkpoint",
    "out_png": "out_file",
    "out_csv": "out_file",
    "out_json": "out_file",
}
"""The kind of input of every slot: the key of its good value in the ``good`` fixture and of its variants in BAD."""

OUTPUTS = {"out_folder": "run", "out_pt": "m.pt", "out_png": "p.png", "out_csv": "m.csv", "out_json": "p.json"}
"""The good value of every output slot: a fresh path of this name."""

Variant = Callable[[Path, dict[str, Path]], Path]
"""Makes one malformed input under a fresh folder (its first argument) from the good inputs; returns its path."""


def _write(name: str, content: bytes | str) -> Variant:
    def make(tmp: Path, good: dict[str, Path]) -> Path:
        path = tmp / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        return path

    return make


def _in_folder(variant: Variant) -> Variant:
    """The malformed file of ``variant`` as the one file of a folder (the folder is given)."""

    def make(tmp: Path, good: dict[str, Path]) -> Path:
        (tmp / "folder").mkdir()
        variant(tmp / "folder", good)
        return tmp / "folder"

    return make


def _missing(tmp: Path, good: dict[str, Path]) -> Path:
    return tmp / "missing"


def _directory(tmp: Path, good: dict[str, Path]) -> Path:
    (tmp / "adir").mkdir()
    return tmp / "adir"


def _under_a_file(tmp: Path, good: dict[str, Path]) -> Path:
    (tmp / "afile").write_text("mine")
    return tmp / "afile" / "out.pt"


def _existing_file(tmp: Path, good: dict[str, Path]) -> Path:
    (tmp / "afile").write_text("mine")
    return tmp / "afile"


def _damaged_run(tmp: Path, good: dict[str, Path]) -> Path:
    """A folder whose resume files (what a command reads back to resume) are damaged."""
    folder = tmp / "run"
    (folder / "stages").mkdir(parents=True)
    for name in ("run.json", "collect.json", "evaluate.json", "stages/collect.json"):
        (folder / name).write_bytes(RANDOM)
    (folder / "round.json").write_text('{"model": ')
    return folder


def _npy(name: str, array: np.ndarray) -> Variant:
    def make(tmp: Path, good: dict[str, Path]) -> Path:
        np.save(tmp / name, array)
        return tmp / name

    return make


def _truncated(key: str, name: str) -> Variant:
    """The good input ``key`` (a file, or the first file of a folder) cut in half."""

    def make(tmp: Path, good: dict[str, Path]) -> Path:
        source = good[key] if good[key].is_file() else sorted(good[key].iterdir())[0]
        data = source.read_bytes()
        (tmp / name).write_bytes(data[: len(data) // 2])
        return tmp / name

    return make


def _copy(key: str, name: str) -> Variant:
    def make(tmp: Path, good: dict[str, Path]) -> Path:
        shutil.copyfile(good[key], tmp / name)
        return tmp / name

    return make


def _record(name: str, **changes) -> Variant:
    """A record ``.npz`` with fields replaced (an array, or a callable of the good field)."""

    def make(tmp: Path, good: dict[str, Path]) -> Path:
        with np.load(sorted(good["records"].iterdir())[0]) as f:
            arrays = dict(f)
        for field, change in changes.items():
            arrays[field] = change(arrays[field]) if callable(change) else change
        np.savez(tmp / name, **arrays)
        return tmp / name

    return make


def _save_without(field: str) -> Variant:
    """A record ``.npz`` without ``field``."""

    def make(tmp: Path, good: dict[str, Path]) -> Path:
        with np.load(sorted(good["records"].iterdir())[0]) as f:
            arrays = {k: v for k, v in f.items() if k != field}
        np.savez(tmp / "without.npz", **arrays)
        return tmp / "without.npz"

    return make


def _with_config(key: str, change: Callable[[dict], object] | bytes | str | None) -> Variant:
    """The good checkpoint ``key`` with its JSON config beside it changed (a callable of its dict), replaced or removed."""

    def make(tmp: Path, good: dict[str, Path]) -> Path:
        path = tmp / good[key].name
        shutil.copyfile(good[key], path)
        meta = json.loads(good[key].with_suffix(".json").read_text())
        if callable(change):
            change(meta["config"])
            path.with_suffix(".json").write_text(json.dumps(meta))
        elif change is not None:
            _write(path.with_suffix(".json").name, change)(tmp, good)
        return path

    return make


def _set(field: str, value: object) -> Callable[[dict], None]:
    return lambda config: config.__setitem__(field, value)


def _checkpoint(name: str, content: object) -> Variant:
    def make(tmp: Path, good: dict[str, Path]) -> Path:
        torch.save(content, tmp / name)
        return tmp / name

    return make


RANDOM = np.random.default_rng(0).bytes(512)
"""Random bytes: what a damaged or wrong file looks like."""
FILE = {
    "missing": _missing,
    "empty": _write("empty.json", ""),
    "random bytes": _write("random.json", RANDOM),
    "a folder": _directory,
}
"""What any input file can be instead."""
MAPPING = {
    **FILE,
    "truncated JSON": _write("cut.json", '{"a": [1, 2'),
    "truncated YAML": _write("cut.yaml", "a: [1, 2\nb: {c"),
    "a list, not a mapping": _write("list.yaml", "- 1\n- 2\n"),
    "unknown field": _write("unknown.yaml", "no_such_field: 1\n"),
}
"""What any YAML/JSON settings file can be instead."""
REFS_FILE = {
    "empty .npy": _write("empty.npy", b""),
    "random .npy": _write("random.npy", RANDOM),
    "random .csv": _write("random.csv", RANDOM),
    "text .csv": _write("text.csv", "boom,arm,bucket,swing\na,b,c,d\n"),
    "truncated .npy": _truncated("refs", "cut.npy"),
    "NaN": _npy("nan.npy", np.full((40, 4), np.nan)),
    "degrees, not radians": _npy("deg.npy", np.full((40, 4), 45.0)),
    "3 joints": _npy("three.npy", np.zeros((40, 3))),
    "one step": _npy("one.npy", np.zeros((1, 4))),
    "ints": _npy("int.npy", np.zeros((40, 4), dtype=np.int64)),
    "unknown suffix": _write("ref.txt", "0,0,0,0\n"),
}
RECORDS_FILE = {
    "empty .npz": _write("empty.npz", b""),
    "random .npz": _write("random.npz", RANDOM),
    "random .csv": _write("random.csv", RANDOM),
    "random .npy": _write("random.npy", RANDOM),
    "truncated .npz": _truncated("records", "cut.npz"),
    "NaN": _record("nan.npz", q=lambda q: q * np.nan),
    "qd 1e300": _record("fast.npz", qd=lambda qd: qd + 1e300),
    "degrees": _record("deg.npz", q=lambda q: q + 90.0),
    "meta not JSON": _record("meta.npz", meta_json=np.array("{'name':")),
    "name leading outside": _record("up.npz", meta_json=np.array('{"name": "../../x"}')),
    "q missing": _save_without("q"),
    "unknown suffix": _write("ep.txt", "1,2,3\n"),
}


CHECKPOINT = {
    **FILE,
    "truncated": None,  # filled per kind below
    "a zip bomb": _copy("bomb", "bomb.pt"),
    "a list": _checkpoint("list.pt", [1, 2, 3]),
    "a dict of strings": _checkpoint("strings.pt", {"state": "x", "config": "y"}),
    "a JSON file": _write("model.json", "{}"),
}
BAD: dict[str, dict[str, Variant]] = {
    "refs": {"missing": _missing, "empty folder": _directory, **REFS_FILE}
    | {f"folder of {name}": _in_folder(REFS_FILE[name]) for name in ("random .npy", "text .csv", "truncated .npy", "NaN")},
    "records": {"missing": _missing, "empty folder": _directory, **RECORDS_FILE}
    | {f"folder of {name}": _in_folder(RECORDS_FILE[name]) for name in ("random .npz", "truncated .npz", "NaN")},
    **{
        kind: {
            **CHECKPOINT,
            "truncated": _truncated(kind, "cut.pt"),
            "the other kind": _copy(other, f"{other}.pt"),
            "config missing": _with_config(kind, None),
            "config random bytes": _with_config(kind, RANDOM),
            "config truncated": _with_config(kind, '{"kind": "'),
            "config NaN": _with_config(kind, _set("lr", float("nan"))),
            "config huge": _with_config(kind, _set("hidden", 10**9)),
            "config wrong type": _with_config(kind, _set("layers", "two")),
        }
        for kind, other in (("model", "policy"), ("policy", "model"))
    },
    "study": {"missing": _missing, "empty folder": _directory, "a file": _write("study.json", "{}")},
    "config": {
        **MAPPING,
        "wrong-typed field": _write("typed.yaml", "model:\n  hidden: big\n"),
        "NaN": _write("nan.yaml", "model:\n  lr: .nan\n"),
        "NaN in JSON": _write("nan.json", '{"model": {"lr": NaN}}'),
        "out of range": _write("range.yaml", "policy:\n  horizon: 100000\n"),
        "huge network": _write("huge.yaml", "model:\n  hidden: 1e9\n"),
        "negative steps": _write("steps.yaml", "model:\n  steps: -5\n"),
        "a list for a section": _write("section.yaml", "model: [1, 2]\n"),
    },
    "pd": {
        **{name: v for name, v in FILE.items() if name != "missing"},  # a missing --pd file reads as a preset name
        "no preset, no file": _missing,
        "truncated JSON": _write("cut.json", '{"kp": [1, 2'),
        "kp a string": _write("kp.json", '{"kp": "x", "kd": [0, 0, 0, 0], "sign": [1, 1, 1, 1]}'),
        "kp NaN": _write("nan.json", '{"kp": [NaN, 1, 1, 1], "kd": [0, 0, 0, 0], "sign": [1, 1, 1, 1]}'),
        "kp 3 joints": _write("three.json", '{"kp": [1, 1, 1], "kd": [0, 0, 0, 0], "sign": [1, 1, 1, 1]}'),
        "u_max negative": _write("umax.json", '{"kp": [1, 1, 1, 1], "kd": [0, 0, 0, 0], "sign": [1, 1, 1, 1], "u_max": -5}'),
        "a list": _write("list.json", "[1, 2]"),
    },
    "limits": {
        **MAPPING,
        "NaN": _write("nan.yaml", "q_min: [.nan, -1, -1, -1]\n"),
        "q_min above q_max": _write("swap.yaml", "q_min: [1, -1, -1, -1]\nq_max: [0, 1, 1, 1]\n"),
        "a string": _write("str.yaml", "max_adjust: wide\n"),
        "3 joints": _write("three.yaml", "max_adjust: [0.1, 0.1, 0.1]\n"),
        "zero bound": _write("zero.yaml", "max_adjust: [0, 0.1, 0.1, 0.1]\n"),
        "stale_steps 1": _write("stale.yaml", "stale_steps: 1\n"),
    },
    "params": {
        **{name: v for name, v in MAPPING.items() if name not in ("truncated YAML", "a list, not a mapping")},
        "a JSON list": _write("list.json", "[1, 2]"),
        "NaN": None,  # from the good file, below
        "wrong-typed field": None,
    },
    "bag": {
        "missing": _missing,
        "empty folder": _directory,
        "a file": _write("cycle.db3", RANDOM),
        "random metadata": _in_folder(_write("metadata.yaml", RANDOM)),
        "no reference topic": lambda tmp, good: write_bag(tmp / "bag", {"/joint_states": states()}),
        "no joint states": lambda tmp, good: write_bag(tmp / "bag", {"/cmd": references()}),
    },
    "out_folder": {"a file": _existing_file, "under a file": _under_a_file, "damaged resume files": _damaged_run},
    "out_checkpoint": {
        "a folder": _directory,
        "under a file": _under_a_file,
        "ends in .json": lambda tmp, good: tmp / "m.json",
        "no suffix": lambda tmp, good: tmp / "m",
        "a damaged training state": _write("m.state.pt", RANDOM),
    },
    "out_file": {"a folder": _directory, "under a file": _under_a_file},
}
"""Every kind of input's malformed variants."""


def _params_with(name: str, change: Callable[[dict], None]) -> Variant:
    def make(tmp: Path, good: dict[str, Path]) -> Path:
        data = json.loads(good["params"].read_text())
        change(data)
        (tmp / name).write_text(json.dumps(data))
        return tmp / name

    return make


def _first_number_to(value: object) -> Callable[[dict], None]:
    def change(data: dict) -> None:
        key = next(k for k, v in data.items() if isinstance(v, int | float) and not isinstance(v, bool))
        data[key] = value

    return change


BAD["params"]["NaN"] = _params_with("nan.json", _first_number_to(float("nan")))
BAD["params"]["wrong-typed field"] = _params_with("typed.json", _first_number_to("heavy"))

SECOND = ("missing", "empty folder", "folder of NaN")
"""The variants tried on a command's second input of a kind already swept (``{refs2}``, ``{records2}``, ...): the
same loader reads it, so a few show that its errors come through too."""
CASES = [
    pytest.param(command, slot, variant, id=f"{command}:{slot}:{variant}")
    for command, args in COMMANDS.items()
    for slot, kind in SLOTS.items()
    if f"{{{slot}}}" in args
    for variant in (SECOND if slot[-1].isdigit() else BAD[kind])
]


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict[str, Path]:
    """Good inputs of every kind (checkpoints of a 2-step tiny training) and fresh output paths."""
    root = tmp_path_factory.mktemp("good")
    records = [make_record(steps=60, seed=i, name=f"ep{i}") for i in range(3)]
    save_references(sine_refs([40, 50]), root / "refs")
    save_records(records, root / "records")
    g_theta = train_model(dataclasses.replace(MODEL_PRESETS["tiny"], steps=2), records, "cpu", progress=False).model
    pi_phi = train_policy(dataclasses.replace(POLICY_PRESETS["tiny"], steps=2), g_theta, records, "cpu", progress=False)
    save_model(g_theta, root / "model.pt")
    save_policy(pi_phi.policy, root / "policy.pt")
    (root / "config.yaml").write_text("seed: 1\n")
    (root / "study" / "jobs" / "pd-closed-s0").mkdir(parents=True)
    pd_point = {"interaction_steps": 0, "wall_seconds": 0.0, "metrics": compute_metrics(records)}
    (root / "study" / "jobs" / "pd-closed-s0" / "result.json").write_text(
        json.dumps({"method": "pd", "loop": "closed", "seed": 0, "curve": [pd_point]})
    )
    (root / "limits.yaml").write_text("max_adjust: [0.1, 0.1, 0.1, 0.1]\n")
    (root / "pd.json").write_text(json.dumps(dataclasses.asdict(PD_PRESETS["xe75"])))
    shutil.copyfile(preset_path(), root / "params.json")
    with zipfile.ZipFile(root / "model.pt") as archive, zipfile.ZipFile(root / "bomb.pt", "w", compresslevel=1) as bomb:
        for member in archive.infolist():  # the checkpoint compressed, one tensor's data declaring 200 MiB
            data = bytes(200 * 2**20) if member.filename.endswith("data/0") else archive.read(member)
            bomb.writestr(member.filename, data, zipfile.ZIP_DEFLATED)
    return {
        "refs": root / "refs",
        "refs2": root / "refs",
        "records": root / "records",
        "records2": root / "records",
        "records3": root / "records",
        "model": root / "model.pt",
        "policy": root / "policy.pt",
        "config": root / "config.yaml",
        "pd": root / "pd.json",
        "limits": root / "limits.yaml",
        "params": root / "params.json",
        "bomb": root / "bomb.pt",
        "study": root / "study",
        "bag": write_bag(root / "cycle_01", {"/joint_states": states(), "/cmd": references()}),
    }


@pytest.fixture(scope="module")
def cases_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("cases")


@pytest.fixture
def case_dir(cases_root, monkeypatch) -> Path:
    """A fresh folder for one case of a sweep, made the working directory (a command's default paths land there), and
    the output checks' probe files not fsynced: pytest's numbered ``tmp_path`` (~5 ms) and the probe's fsync (~6 ms on
    a disk) were most of a case's time. A full disk has its own test (test_a_disk_full_at_the_final_write_...)."""
    folder = Path(tempfile.mkdtemp(dir=cases_root))
    monkeypatch.chdir(folder)
    monkeypatch.setattr(os, "fsync", lambda fd: None)
    return folder


def run_main(argv: list[str], monkeypatch, capsys) -> tuple[int | str | None, str]:
    """Run ``efficienttrack ARGV`` through :func:`efficienttrack.cli.main`; return its exit code and its stderr."""
    monkeypatch.setattr(sys, "argv", ["efficienttrack", *argv])
    monkeypatch.setattr(cli, "app", click_command())
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)  # main() sets its own; put it back after
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    return exit_info.value.code, capsys.readouterr().err


def one_line_error(code: int | str | None, err: str) -> str:
    """The one error line of a refused command (warnings aside), after checking exit code 2 and that it is one line."""
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("warning:")]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), f"exit code {code}, stderr:\n{err}"
    return lines[0]


@pytest.mark.parametrize(("command", "slot", "variant"), CASES)
def test_every_command_refuses_a_bad_file_in_one_line(command, slot, variant, good, case_dir, monkeypatch, capsys):
    (case_dir / "bad").mkdir()
    bad = BAD[SLOTS[slot]][variant](case_dir / "bad", good)
    if bad.name.endswith(".state.pt"):  # a damaged training state beside the checkpoint given
        bad = bad.with_name(bad.name.removesuffix(".state.pt") + ".pt")
    paths = {**good, **{slot_: case_dir / "out" / name for slot_, name in OUTPUTS.items()}, slot: bad}
    argv = [arg.format(**paths) for arg in COMMANDS[command].split()]
    line = one_line_error(*run_main(argv, monkeypatch, capsys))
    assert bad.name in line or str(bad.parent) in line, line  # the error is about the bad input, and names it


OPTIONS = [
    ("refs generate", "--n", "0"),
    ("refs generate", "--n", "-3"),
    ("refs generate", "--preset", "nosuch"),
    ("metrics", "--pool", "--per-episode"),
    ("convert", "--format", "xls"),
    ("convert", "--max-gap", "0.01"),
    ("convert", "--time-unit", "min"),
    ("convert", "--angle-unit", "grad"),
    ("convert", "--column", "q.elbow=X"),
    ("collect", "--passes", "0"),
    ("collect", "--sigma-max", "nan"),
    ("collect", "--sigma-max", "-1"),
    ("collect", "--noise-ratio", "1:0:2"),
    ("collect", "--noise-ratio", "a:b"),
    ("collect", "--plant", "nosuch"),
    ("collect", "--plant", "no.such.module:make"),
    ("collect", "--seed", "-1"),
    ("collect", "--system-opt", "payload"),
    ("collect", "--system-opt", "payload=7"),
    ("collect", "--system-opt", "no_such_option=1"),
    ("evaluate", "--device", "tpu"),
    ("evaluate", "--plots", "-1"),
    ("run", "--round-data", "some"),
    ("demo", "--seed", "-1"),
    ("run", "--seed", "-1"),
    ("train-model", "--steps", "0"),
    ("train-model", "--steps", "-5"),
    ("train-model", "--threads", "-1"),
    ("train-model", "--seed", "-1"),
    ("train-model", "--preset", "huge"),
    ("train-model", "--device", "cuda:99"),
    ("model-error", "--steps", "0"),
    ("model-error", "--steps", "100000"),
    ("train-policy", "--steps", "0"),
    ("train-policy", "--seed", "-1"),
    ("round", "--warm-budget", "nan"),
    ("round", "--warm-budget", "0"),
    ("run", "--set", "model.history=0"),
    ("demo", "--set", "seed=-1"),
    ("train-model", "--set", "model.lr=1e300"),
    ("train-model", "--set", "model.hidden"),
    ("train-policy", "--set", "policy.nosuch=1"),
    ("round", "--set", "warm_budget=[1"),
    ("study", "--set", "collect.passes=0"),
    ("study", "--preset", "huge"),
    ("ablate", "--set", "device=tpu"),
    ("config show", "--set", "rounds=0"),
    ("sim calibrate", "--delays", "-1"),
    ("sim calibrate", "--delays", "a,b"),
    ("sim calibrate", "--max-windows", "0"),
    ("sim calibrate", "--max-nfev", "0"),
    ("sim calibrate", "--max-ref-jitter", "nan"),
    ("sim fidelity", "--stride", "0"),
    ("sim fidelity", "--episodes", "-1"),
    ("sim fidelity", "--min-ref-jitter", "nan"),
    ("sim fidelity", "--max-ref-jitter", "-1"),
    ("limits", "--margin", "-1"),
    ("limits", "--margin", "nan"),
    ("limits", "--speed-factor", "0.5"),
]
"""Out-of-range and malformed option values, each added to a command's good arguments (the last value given counts)."""


FILE_OPTIONS_ONLY = {"refs plot", "export", "import-rosbag", "deploy", "study-plot"}
"""Commands with no case in :data:`OPTIONS`: their value options are swept as files above or have their own tests
(``import-rosbag --max-gap`` in test_rosbag, ``deploy``'s rates and modes in test_loop)."""


def test_every_registered_command_is_in_the_sweep():
    def names(command, prefix=""):
        if hasattr(command, "commands"):  # a group: its subcommands
            for name, sub in command.commands.items():
                yield from names(sub, f"{prefix}{name} ")
        else:
            yield prefix.strip()

    registered = set(names(click_command()))
    assert len(registered) >= 20 and "config show" in registered
    assert registered == set(COMMANDS), f"missing from COMMANDS: {registered - set(COMMANDS)}"
    assert {command for command, *_ in OPTIONS} == set(COMMANDS) - FILE_OPTIONS_ONLY


def _registered(app, prefix=""):
    """(name, function) of every command registered on a Typer app and its groups."""
    for command in app.registered_commands:
        yield f"{prefix}{command.name or command.callback.__name__}", command.callback
    for group in app.registered_groups:
        yield from _registered(group.typer_instance, f"{prefix}{group.name} ")


WRITERS = sorted(name for name, function in _registered(cli.app) if "_lock(" in inspect.getsource(function))
"""The registered commands that lock their output (their function takes the lock): found, not listed by hand."""


def test_the_writers_are_found():
    assert {"collect", "run", "train-model", "round", "convert", "import-rosbag", "study", "deploy", "limits",
            "sim calibrate"} <= set(WRITERS)  # fmt: skip


@pytest.mark.parametrize("command", WRITERS)
def test_every_writer_refuses_an_output_another_process_is_writing(command, good, case_dir, monkeypatch, capsys):
    paths = {**good, **{slot: case_dir / "out" / name for slot, name in OUTPUTS.items()}}
    argv = [arg.format(**paths) for arg in COMMANDS[command].split()]
    slot = next(slot for slot in ("out_folder", "out_pt", "out_json") if f"{{{slot}}}" in COMMANDS[command])
    with output_lock(paths[slot], folder=slot == "out_folder"):
        line = one_line_error(*run_main(argv, monkeypatch, capsys))
    assert f"{paths[slot]}: another efficienttrack process" in line and "is writing it" in line, line


@pytest.mark.parametrize(("command", "option", "value"), [pytest.param(*case, id=" ".join(case)) for case in OPTIONS])
def test_every_command_refuses_a_bad_option_value_in_one_line(command, option, value, good, case_dir, monkeypatch, capsys):
    paths = {**good, **{slot: case_dir / "out" / name for slot, name in OUTPUTS.items()}}
    argv = [*(arg.format(**paths) for arg in COMMANDS[command].split()), option, value]
    line = one_line_error(*run_main(argv, monkeypatch, capsys))
    assert option in line or value.split("=")[0] in line, line


# --------------------------------------------------------------------------- the system refusing a file, late


def _full_disk_for_written_files(monkeypatch) -> None:
    """``fsync`` fails with ENOSPC on the temporary files :func:`atomic_write` writes (not on the output checks' probes)."""
    fsync = os.fsync

    def full(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".tmp"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", full)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="finds atomic_write's files through /proc")
def test_a_disk_full_at_the_final_write_is_one_line_naming_the_file(tmp_path, monkeypatch, capsys):
    _full_disk_for_written_files(monkeypatch)
    out = tmp_path / "refs"
    line = one_line_error(*run_main(["refs", "generate", "--out", str(out), "--n", "2"], monkeypatch, capsys))
    assert re.fullmatch(f"error: {re.escape(str(out))}/ref_0[01].npy: No space left on device", line), line
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]  # no temporary file left behind


def test_atomic_write_names_the_destination_and_a_bug_keeps_its_traceback(tmp_path, monkeypatch, capsys):
    def refused(*args, **kwargs):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), "/somewhere/.m.pt.x1y2.tmp")

    monkeypatch.setattr(tempfile, "mkstemp", refused)
    with pytest.raises(PermissionError) as info:
        atomic_write(tmp_path / "m.pt", lambda f: f.write(b"x"))
    assert (info.value.errno, info.value.filename) == (errno.EACCES, str(tmp_path / "m.pt"))

    def bug(*args, **kwargs):
        raise OSError("not the system: a bug")  # no errno

    monkeypatch.setattr(cli.data, "metrics_by_path", bug)
    with pytest.raises(OSError, match="a bug"):
        run_main(["metrics", str(tmp_path)], monkeypatch, capsys)


# ------------------------------------------------------------------------------------ leftovers of issue 16


def test_record_meta_is_written_as_strict_json(tmp_path):
    record = make_record(name="ep")
    record.meta["sigma"] = float("nan")
    with pytest.warns(UserWarning, match="not finite, written as null: sigma"):
        record.save(tmp_path / "ep.npz")
    with np.load(tmp_path / "ep.npz") as f:
        text = str(f["meta_json"])

    def refuse(constant):
        raise ValueError(f"{constant} in meta_json")

    assert json.loads(text, parse_constant=refuse)["sigma"] is None


def test_a_compressed_checkpoint_may_not_expand_beyond_the_limit(tmp_path, monkeypatch):
    torch.save({"w": torch.zeros(2**18)}, tmp_path / "plain.pt")  # 1 MiB of data, stored as torch writes it
    with zipfile.ZipFile(tmp_path / "plain.pt") as archive, zipfile.ZipFile(tmp_path / "small.pt", "w") as small:
        for member in archive.infolist():
            small.writestr(member.filename, archive.read(member), zipfile.ZIP_DEFLATED)
    assert (tmp_path / "small.pt").stat().st_size < 2**14  # the same checkpoint, a few KB
    monkeypatch.setattr(checkpoints, "MAX_EXPANDED_BYTES", 2**19)
    assert load_tensors(tmp_path / "plain.pt")["w"].shape == (2**18,)  # a file may always be as large as it is
    with pytest.raises(EfficientTrackError, match=r"small.pt: refused to load: its \d+-byte archive expands to 1.0 MiB"):
        load_tensors(tmp_path / "small.pt")


def test_collect_refuses_references_outside_the_joint_limits_before_anything_moves(tmp_path):
    machine = LagSystem()
    system = BatchedSystem(machine)
    system.limits = GuardLimits(q_min=(-0.65, -3, -3, -math.pi), q_max=(0.65, 3, 3, math.pi))
    refs = sine_refs([40, 40])
    q = refs[1].q.copy()
    q[:, 0] = 2.5
    refs[1] = Reference("ref_01", q)
    with pytest.raises(EfficientTrackError, match="reference 'ref_01': boom is 2.5 rad at step 0, outside the joint"):
        collect(system, refs, CollectConfig(passes=1), out=tmp_path / "collect", progress=False)
    assert machine._q is None and not (tmp_path / "collect").exists()  # never reset, nothing written


@pytest.mark.parametrize("name", ["m.json", "m", "m.logs"])
def test_a_checkpoint_out_must_end_in_pt_before_any_training(good, tmp_path, monkeypatch, capsys, name):
    out = tmp_path / name
    argv = ["train-model", "--data", str(good["records"]), "--out", str(out), "--preset", "tiny", "--steps", "2"]
    line = one_line_error(*run_main(argv, monkeypatch, capsys))
    assert line.startswith(f"error: --out {out}: a checkpoint must end in .pt") and f"--out {tmp_path / 'm.pt'}" in line
    assert list(tmp_path.iterdir()) == []  # no logs, no state, no config: nothing trained
