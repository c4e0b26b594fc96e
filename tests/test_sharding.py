"""The transport's rows sharded over devices and processes: the same map as one device.

JAX fixes its device count when it starts, so each layout runs `examples/distributed_solve.py`
in its own process (four CPU devices; two processes over a loopback coordinator).
"""

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hiddenjax as hj

SCRIPT = Path(__file__).parent.parent / "examples" / "distributed_solve.py"


def run(out: Path, *extra, processes: int = 1) -> dict:
    """Run the example (float64) in `processes` processes; process 0's results."""
    with socket.socket() as s:  # a free port for the coordinator
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    command = [sys.executable, str(SCRIPT), "--quick", "--x64", "--prior", "l2", "--out", str(out), *extra]
    if processes > 1:
        command += ["--processes", str(processes), "--coordinator", f"127.0.0.1:{port}"]
        runs = [subprocess.Popen(command + ["--process-id", str(k)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                 text=True) for k in range(processes)]
        logs = [r.communicate(timeout=600)[0] for r in runs]
        assert all(r.returncode == 0 for r in runs), "\n".join(logs)
    else:
        done = subprocess.run(command, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stdout + done.stderr
    return json.loads((out / "results.json").read_text()) | {"env": np.load(out / "env.npy")}


@pytest.fixture(scope="module")
def one_device(tmp_path_factory):
    return run(tmp_path_factory.mktemp("one"))


def relative(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_four_devices_give_the_one_device_map(one_device, tmp_path):
    four = run(tmp_path, "--devices", "4")
    assert four["devices"] == 4 and one_device["devices"] == 1
    assert four["rows"] % 4 == 0 and four["rows"] >= one_device["rows"]  # padded with empty rows
    assert relative(four["env"], one_device["env"]) < 1e-10
    assert one_device["kkt_residual"] < 1e-8


@pytest.mark.slow
def test_two_processes_give_the_one_process_map(one_device, tmp_path):
    two = run(tmp_path, processes=2)
    assert two["processes"] == 2 and two["devices"] == 2
    assert relative(two["env"], one_device["env"]) < 1e-10


def test_padded_rows_read_zero_and_are_dropped(small_setup):
    """The empty rows that pad a sharded matrix (pixel H * W) do not touch images."""
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, hj.EnvGrid(8, 16), samples=2, progress=False)
    H, W = T.image_shape
    padded = hj.TransportMatrix(A=np.pad(np.asarray(T.A), ((0, 3), (0, 0))),
                                albedo=np.pad(np.asarray(T.albedo), (0, 3), constant_values=1.0),
                                pixels=np.pad(np.asarray(T.pixels), (0, 3), constant_values=H * W),
                                grid=T.grid, image_shape=T.image_shape)
    image = np.random.default_rng(0).random((H, W, 3)).astype(np.float32) + 1
    rows = np.asarray(padded.image_to_rows(image))
    assert np.array_equal(rows[:-3], np.asarray(T.image_to_rows(image))) and np.all(rows[-3:] == 0)
    assert np.array_equal(padded.mask, T.mask)
    filled = np.asarray(padded.rows_to_image(np.ones((len(rows), 3), np.float32)))
    assert np.array_equal(filled[..., 0] > 0, T.mask)
    env = np.ones(T.grid.shape, np.float32)
    assert np.allclose(np.asarray(hj.render(padded, env)), np.asarray(hj.render(T, env)))


def test_shard_refuses_no_devices(small_setup):
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, hj.EnvGrid(8, 16), samples=2, progress=False)
    with pytest.raises(ValueError, match="devices is empty"):
        hj.transport.shard(T, devices=[])
