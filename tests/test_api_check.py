"""The top-level Python API refuses a wrong argument with one EfficientTrackError naming it (core/api_check.py)."""

import subprocess
import sys

import numpy as np
import pytest

import efficienttrack as et
from efficienttrack.core.errors import EfficientTrackError


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: et.load_system(5), "load_system: argument 'spec' must be a string, got int 5"),
        (lambda: et.load_plant(None), "load_plant: argument 'spec' must be a string, got NoneType None"),
        (lambda: et.load_references(None), "load_references: argument 'source' must be a string or a path or a list"),
        (lambda: et.load_records(None), "load_records: argument 'paths' must be a string or a path or a list"),
        (lambda: et.load_policy(3), "load_policy: argument 'path' must be a string or a path, got int 3"),
        (lambda: et.load_model(None), "load_model: argument 'path' must be a string or a path, got NoneType None"),
        (lambda: et.export("/path"), "export: missing a required argument: 'out'"),
        (lambda: et.generate_references("a", seed=1), "generate_references: argument 'n' must be an integer, got str"),
        (lambda: et.generate_references(2, seed=1, colour="red"), "got an unexpected keyword argument 'colour'"),
        (lambda: et.compute_metrics("x"), "compute_metrics: argument 'records' must be a sequence"),
        (lambda: et.run(1, [], [], "out", et.preset("tiny")), "run: argument 'system' must be a SystemSpec, got int 1"),
        (lambda: et.preset(5), "preset: argument 'name' must be a string, got int 5"),
    ],
)
def test_a_wrong_argument_is_one_error_naming_it(call, message):
    with pytest.raises(EfficientTrackError, match="efficienttrack.") as info:
        call()
    assert message in str(info.value)


def test_right_arguments_pass_numpy_integers_and_paths_included(tmp_path):
    refs = et.generate_references(np.int64(2), seed=0)
    assert [r.name for r in refs] == ["ref_01", "ref_02"]
    assert et.preset("tiny").model.steps == et.preset(name="tiny").model.steps
    assert et.load_system("paper").dt == 0.05


def test_on_the_core_install_the_api_names_the_extra_to_install():
    torch_free = (
        "import sys; sys.modules['torch'] = None\n"  # an import of torch fails as on an install without it
        "import efficienttrack as et\n"
        "from efficienttrack.core.errors import MissingExtraError\n"
        "for name in ('train_model', 'load_policy', 'run'):\n"
        "    try:\n"
        "        getattr(et, name)\n"
        "    except MissingExtraError as exc:\n"
        "        print(exc)\n"
        "print(et.load_references.__name__)\n"  # what needs no torch still works
    )
    done = subprocess.run([sys.executable, "-c", torch_free], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        *(f"efficienttrack.{name} needs torch, which is not installed: pip install 'efficienttrack[train]' (in a clone "
          "of the repository: pip install '.[train]')" for name in ("train_model", "load_policy", "run")),
        "load_references",
    ]  # fmt: skip
