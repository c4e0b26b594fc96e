"""Every example and benchmark runs with --quick and writes results.json (docs/conventions.md, "Scripts")."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Scripts whose --quick run takes half a minute or more on 2 cores: run with -m slow (CI runs them).
LONG = {"around_the_corner.py", "uncertain_scene.py", "bench_shadows.py", "bench_corners.py", "bench_weight_choice.py",
        "real_capture.py", "bench_scale.py", "distributed_solve.py", "design_occluder.py", "ablation.py",
        "bench_compile.py", "bench_robustness.py", "train_corner_networks.py"}


def scripts(folder):
    return [pytest.param(p, marks=[pytest.mark.slow] if p.name in LONG else [], id=f"{folder}/{p.name}")
            for p in sorted((ROOT / folder).glob("*.py"))
            if not p.name.startswith("_")]  # _report.py is a shared module, not a script


def run_quick(script, tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, str(script), "--quick", "--out", str(tmp_path)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads((tmp_path / "results.json").read_text())
    assert results, "results.json is empty"
    assert list(tmp_path.glob("*.png")), "no picture written"


# One class per folder: `--dist loadscope` hands each class to a worker of its own (the scripts run in
# their own processes and share nothing with each other's tests, so they need not queue on one worker).
class TestExamples:
    @pytest.mark.parametrize("script", scripts("examples"))
    def test_script_runs_quick(self, script, tmp_path):
        run_quick(script, tmp_path)


class TestBenchmarks:
    @pytest.mark.parametrize("script", scripts("benchmarks"))
    def test_script_runs_quick(self, script, tmp_path):
        run_quick(script, tmp_path)
