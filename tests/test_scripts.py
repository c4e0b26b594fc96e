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
        "bench_compile.py", "bench_robustness.py", "train_corner_networks.py", "bench_tables.py"}


def scripts(folder, long):
    """The folder's scripts in LONG (`long=True`) or not in it."""
    return [p for p in sorted((ROOT / folder).glob("*.py"))
            if not p.name.startswith("_") and (p.name in LONG) == long]  # _report.py is a shared module


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


# `--dist loadscope` hands each class to one worker. The quick scripts: one class per folder (they run in
# their own processes and share nothing with each other's tests, so they need not queue on one worker).
# The long ones: one class each, so that the slow run spreads them over the workers (in one class they
# queued on one worker for 25 of the slow run's 28 minutes, 2 cores).
class TestExamples:
    @pytest.mark.parametrize("script", scripts("examples", long=False), ids=lambda p: f"examples/{p.name}")
    def test_script_runs_quick(self, script, tmp_path):
        run_quick(script, tmp_path)


class TestBenchmarks:
    @pytest.mark.parametrize("script", scripts("benchmarks", long=False), ids=lambda p: f"benchmarks/{p.name}")
    def test_script_runs_quick(self, script, tmp_path):
        run_quick(script, tmp_path)


def _long_script_test(script):
    @pytest.mark.slow
    class TestLongScript:
        def test_script_runs_quick(self, tmp_path):
            run_quick(script, tmp_path)
    TestLongScript.__name__ = TestLongScript.__qualname__ = f"TestLong_{script.parent.name}_{script.stem}"
    return TestLongScript


for _script in scripts("examples", long=True) + scripts("benchmarks", long=True):
    globals()[f"TestLong_{_script.parent.name}_{_script.stem}"] = _long_script_test(_script)


@pytest.mark.slow
def test_run_gpu_runs_the_steps_named_and_writes_both_platforms(tmp_path):
    """`RUN_GPU_STEPS` picks the steps of `benchmarks/run_gpu.sh`; each platform's run lands in OUT/gpu.json.

    Without a GPU the `cuda,cpu` run fails (its status says so) and the CPU platform's runs."""
    env = dict(os.environ, RUN_GPU_STEPS="bench_video", PYTHON=sys.executable, RUN_GPU_BUDGET_S="300")
    proc = subprocess.run(["bash", str(ROOT / "benchmarks" / "run_gpu.sh"), str(tmp_path), "--quick"], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = json.loads((tmp_path / "gpu.json").read_text())
    assert set(table) == {"bench_video"}, table.keys()  # the demo and the other steps did not run
    cpu = table["bench_video"]["cpu"]
    assert cpu["rc"] == 0 and cpu["results"], cpu
    assert "cuda,cpu" in table["bench_video"]
