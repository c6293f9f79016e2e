"""A run on CUDA where a GPU is present (CI and the project's machines have none: these tests skip there).

The checks a GPU machine owes the CPU-only suite: ``--device auto`` takes the GPU, a whole run trains and deploys on it,
and what it saves runs unchanged on a CPU (a policy trained on a workstation's GPU goes to the machine's computer).
"""

import json
from dataclasses import replace

import pytest
import torch

from efficienttrack.learn import policy
from efficienttrack.learn.nets import resolve_device
from efficienttrack.workflow.evaluation import evaluate
from efficienttrack.workflow.pipeline import run_pipeline
from toy_system import TOY, TOY_CFG

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")


def test_auto_takes_the_gpu():
    assert resolve_device("auto").type == "cuda"


def test_a_run_on_the_gpu_beats_pd_and_its_policy_tracks_alike_on_a_cpu(tmp_path, toy_refs):
    out = tmp_path / "run"
    result = run_pipeline(TOY, *toy_refs, out, replace(TOY_CFG, device="auto"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == json.loads(json.dumps(result.metrics))
    assert metrics["provenance"]["device"].startswith("cuda")
    assert metrics["efficienttrack"]["mae_deg"] < 0.8 * metrics["pd"]["mae_deg"]

    on_cpu = evaluate(TOY, toy_refs[1], tmp_path / "cpu", policy_path=out / "policy.pt", device="cpu", max_plots=0)
    assert on_cpu["provenance"]["device"] == "cpu"
    assert on_cpu["efficienttrack"]["mae_deg"] == pytest.approx(metrics["efficienttrack"]["mae_deg"], rel=1e-3)
    assert next(policy.load_policy(out / "policy.pt", device="cpu").parameters()).device.type == "cpu"
