"""The persistent compilation cache: off on import, on in one call, private, shared safely, and a warning when unusable."""

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax._compilation_cache import PROGRAMS, _unusable, trim

# A small program under the cache; prints what JAX's monitoring saw (hits, compilations) and the result.
PROBE = """
import json, sys
import jax
from jax import monitoring
events = []
monitoring.register_event_listener(lambda name, **kw: events.append(name))
import hiddenjax as hj
import jax.numpy as jnp
before = None if jax.config.jax_compilation_cache_dir is None else str(jax.config.jax_compilation_cache_dir)
folder = hj.enable_compilation_cache()
x = jax.jit(lambda a: jnp.linalg.cholesky(a @ a.T + 3 * jnp.eye(a.shape[0])).sum())(jnp.arange(36.0).reshape(6, 6) / 36)
print(json.dumps(dict(before=before, folder=None if folder is None else str(folder), value=float(x),
                      hits=events.count("/jax/compilation_cache/cache_hits"),
                      misses=events.count("/jax/compilation_cache/cache_misses"))))
"""


def probe(env_cache, extra_env=None):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")
           and not k.startswith("JAX_PERSISTENT_CACHE")}
    env.update(JAX_PLATFORMS="cpu", **({} if env_cache is None else {"HIDDENJAX_CACHE": str(env_cache)}),
               **(extra_env or {}))
    done = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def test_import_leaves_jax_alone_and_a_second_process_loads_the_program_but_never_a_half_written_one(tmp_path):
    cache = tmp_path / "cache"
    first, _ = probe(cache)
    assert first["before"] is None  # importing hiddenjax set no cache
    assert first["folder"] == str(cache) and first["hits"] == 0 and first["misses"] >= 1
    assert oct(cache.stat().st_mode & 0o777) == oct(0o700)  # private: the cache is trusted
    assert [p for p in cache.iterdir() if p.name.endswith("-cache")], "no program written"
    second, _ = probe(cache)
    assert second["hits"] >= 1 and second["misses"] == 0
    assert second["value"] == first["value"]
    # What a process reads while another writes the entry (JAX writes in place, no lock): every entry cut to half.
    for p in cache.iterdir():
        if p.name.endswith("-cache"):
            p.write_bytes(p.read_bytes()[:p.stat().st_size // 2])
    third, stderr = probe(cache)
    assert third["hits"] == 0 and third["value"] == first["value"]
    assert "Error reading persistent compilation cache" in stderr


def test_off_and_default_folder(tmp_path):
    off, _ = probe("off")
    assert off["folder"] is None and off["hits"] == 0
    default, _ = probe(None, dict(XDG_CACHE_HOME=str(tmp_path)))
    assert Path(default["folder"]).parent == tmp_path / "hiddenjax"
    assert Path(default["folder"]).name.startswith("jax-")


def test_concurrent_processes_fill_one_cache(tmp_path):
    cache = tmp_path / "shared"
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(JAX_PLATFORMS="cpu", HIDDENJAX_CACHE=str(cache))
    runs = [subprocess.Popen([sys.executable, "-c", PROBE], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True) for _ in range(3)]
    outs = [r.communicate(timeout=300) for r in runs]
    assert all(r.returncode == 0 for r in runs), [o[1][-1000:] for o in outs]
    values = {json.loads(o[0].strip().splitlines()[-1])["value"] for o in outs}
    assert len(values) == 1
    again, stderr = probe(cache)
    assert again["hits"] >= 1 and again["value"] in values
    assert "Error reading persistent compilation cache" not in stderr


def test_trim_removes_the_least_recently_used_programs_beyond_the_maximum(tmp_path):
    folder = tmp_path / "cache"
    folder.mkdir()
    for k in range(6):  # JAX's entries, 1000 bytes each, used at times 1000 + k (k = 5 the latest)
        for suffix in ("-cache", "-atime"):
            (folder / f"key{k}{suffix}").write_bytes(b"x" * (1000 if suffix == "-cache" else 8))
            os.utime(folder / f"key{k}{suffix}", (1000 + k, 1000 + k))
    (folder / PROGRAMS).mkdir()  # hiddenjax's own store, trimmed by itself
    assert trim(folder, max_bytes=3500) == 3000
    assert sorted(p.name for p in folder.iterdir() if p.name.endswith("-cache")) == ["key3-cache", "key4-cache",
                                                                                     "key5-cache"]
    assert not (folder / "key0-atime").exists() and (folder / "key3-atime").exists() and (folder / PROGRAMS).is_dir()
    assert trim(folder, max_bytes=0) == 0  # listed at most once per `every_s`: the marker is fresh
    assert trim(folder, max_bytes=0, every_s=0) == 3000
    assert trim(tmp_path / "missing", every_s=0) == 0


def test_the_program_store_keeps_its_latest_entries_within_its_maximum(tmp_path, monkeypatch):
    from hiddenjax import _program_store

    monkeypatch.setattr(_program_store, "MAX_BYTES", 2500)
    for k in range(2):  # written at times 1000 and 1001, 2000 bytes in all
        _program_store._write(tmp_path / f"program{k}", b"x" * 1000)
        os.utime(tmp_path / f"program{k}", (1000 + k, 1000 + k))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["program0", "program1"]
    _program_store._write(tmp_path / "program2", b"x" * 1000)  # 3000 bytes: the oldest goes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["program1", "program2"]


def test_unusable_folders_warn_and_run_without(tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    assert "cannot create" in _unusable(a_file / "cache")
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert "can be written by other users" in _unusable(shared)
    assert _unusable(tmp_path / "fresh") is None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert hj.enable_compilation_cache(a_file / "cache") is None
    assert any("will not be cached" in str(w.message) and "HIDDENJAX_CACHE" in str(w.message) for w in caught)


def test_cli_runs_with_an_unwritable_cache(tmp_path):
    """The command warns in one line and still does its work."""
    a_file = tmp_path / "file"
    a_file.write_text("x")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(JAX_PLATFORMS="cpu", HIDDENJAX_CACHE=str(a_file / "cache"))
    done = subprocess.run([sys.executable, "-m", "hiddenjax.cli", "board", "-o", str(tmp_path / "board.png")],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "will not be cached" in lines[0], done.stderr
    assert (tmp_path / "board.png").exists()


# Programs traced and lowered in this process (counted whether or not the disk cache then answers).
_lowered = []
jax_monitoring_registered = False


def lowered_programs(fn):
    """How many JAX programs `fn()` traces and lowers."""
    global jax_monitoring_registered
    from jax import monitoring
    if not jax_monitoring_registered:
        monitoring.register_event_duration_secs_listener(
            lambda name, secs, **_: _lowered.append(name) if name == "/jax/core/compile/jaxpr_to_mlir_module_duration"
            else None)
        jax_monitoring_registered = True
    before = len(_lowered)
    fn()
    return len(_lowered) - before


def test_a_solve_and_the_cues_are_a_few_programs_compiled_once_for_every_weight(small_setup):
    """Compile once: the build is one program, the default prior's solve four (the solver's own, shared by
    every L2 prior, and the small steps around it), new photos and weights reuse them, and the cue maps
    share one factorization (two programs: its starting factors, then their refinement) and add one of
    their own (eager array glue once made a first solve ~80 programs)."""
    import numpy as np
    grid = hj.EnvGrid(4, 8)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, grid, samples=4, pixel_samples=1)
    sky = hj.scenes.procedural_sky(32, 64)
    photo = np.asarray(hj.render(T, grid.downsample(sky)))
    import jax.numpy as jnp

    jnp.asarray(0.5)  # JAX's transfer of a Python number (a program of its own, once per process, whoever asks)
    first = lowered_programs(lambda: np.asarray(hj.solve_illumination(T, photo).env))
    assert first <= 5, first
    hj.solve_illumination(T, photo, prior=hj.solvers.L2Prior(smooth=0.2))  # L2 without reweighting: its own steps
    # other photos, and other weights (the smoothness, ridge and floor are arguments; `adapt`, `reweight`
    # and `threshold` choose the program's form and are static)
    hdr = lambda floor: hj.solvers.L2Prior(smooth=0.5, ridge=1e-3, floor=floor, reweight=3, threshold=0.02, adapt=0.4)
    again = lowered_programs(lambda: [np.asarray(hj.solve_illumination(T, photo * s, prior=p).env)
                                      for s in (0.5, 2.0) for p in (hdr(0.1), hdr(0.5),
                                                                    hj.solvers.L2Prior(smooth=0.01, ridge=1e-3))])
    assert again == 0, again
    cues = lowered_programs(lambda: [np.asarray(hj.cues.leverage(T, ridge=r)) for r in (1e-4, 1e-3)])
    assert cues <= 3, cues


def test_a_later_solve_on_an_operator_compiles_nothing(small_setup):
    """On a `TransportOperator` (products on the host) the solve runs eagerly around compiled steps: a
    reweighting loop left to `fori_loop` was traced and compiled again for every photo."""
    import numpy as np
    grid = hj.EnvGrid(4, 8)
    op = hj.transport_operator(small_setup.scene, small_setup.camera, grid, samples=4, pixel_samples=1,
                               progress=False)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, grid, samples=4, pixel_samples=1, progress=False)
    photo = np.asarray(hj.render(T, grid.downsample(hj.scenes.procedural_sky(32, 64))))
    first = hj.solve_illumination(op, photo)
    hdr = lambda floor: hj.solvers.L2Prior(smooth=0.5, ridge=1e-3, floor=floor, reweight=3, threshold=0.02, adapt=0.4)
    hj.solve_illumination(op, photo, prior=hdr(0.1))
    again = lowered_programs(lambda: [np.asarray(hj.solve_illumination(op, photo * s, prior=p).env)
                                      for s in (0.5, 2.0) for p in (None, hdr(0.3))])
    assert again == 0, again
    # the same map as the dense matrix's compiled solve (the operator's rows are the matrix's)
    dense = hj.solve_illumination(T, photo)
    assert float(jnp.max(jnp.abs(first.env - dense.env)) / jnp.max(dense.env)) < 1e-4


def test_the_albedo_solve_is_one_program_for_every_photo_and_weight(small_setup):
    """`solve_albedo_illumination` is one compiled program per shapes: its alternation traced eagerly was a
    new closure, compiled again on every call (about 2 s each at 64x64)."""
    import numpy as np
    grid = hj.EnvGrid(4, 8)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, grid, samples=4, pixel_samples=1, progress=False)
    skies = [hj.scenes.procedural_sky(32, 64, sun=(0.8, phi)) for phi in (0.5, 2.5)]
    photos = np.stack([np.asarray(hj.render(T, grid.downsample(sky))).mean(-1) for sky in skies])
    first = hj.solvers.solve_albedo_illumination(T, photos, max_steps=4, throw=False)
    assert first.env.shape == (2,) + grid.shape and first.objective_history.shape == (4,)
    again = lowered_programs(lambda: [np.asarray(hj.solvers.solve_albedo_illumination(
        T, photos * s, smooth=w, albedo_ridge=r, max_steps=4, throw=False).env) for s, w, r in ((0.5, 1e-3, 0.1), (2.0, 1e-2, 0.3))])
    assert again == 0, again


SOLVE_PROBE = """
import json
import numpy as np
from jax import monitoring
events = []
monitoring.register_event_listener(lambda name, **kw: events.append(name))
import hiddenjax as hj
from hiddenjax import _qp
traced = []  # the exact solver's traces: none where its program comes from the store
_qp.solve_from = lambda *a, f=_qp.solve_from, **k: traced.append(1) or f(*a, **k)
hj.enable_compilation_cache()
setup = hj.scenes.object_on_plane("sphere", width=16, height=16)
grid = hj.EnvGrid(4, 8)
T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=2, pixel_samples=1, progress=False)
photo = np.asarray(hj.render(T, grid.downsample(hj.scenes.procedural_sky(32, 64))))
start = len(events)
env = np.asarray(hj.solve_illumination(T, photo).env)
cues = np.asarray(hj.cues.leverage(T))
later = events[start:]
print(json.dumps(dict(misses=later.count("/jax/compilation_cache/cache_misses"),
                      hits=later.count("/jax/compilation_cache/cache_hits"), env=float(env.sum()),
                      solver_traces=len(traced), stored=len(list(hj.enable_compilation_cache().glob("*/_solve-*"))))))
"""


def test_the_solve_and_the_cues_are_loaded_from_the_cache_in_a_second_process(tmp_path):
    """Their programs carry no host callback (JAX keys those on the callback's address in one process, so a
    later process never finds them): the checks run on the host. Nor are they traced again."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(JAX_PLATFORMS="cpu", HIDDENJAX_CACHE=str(tmp_path / "cache"))
    runs = []
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", SOLVE_PROBE], env=env, capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    assert runs[0]["misses"] >= 3  # the build, the solve, the cue factorization and map: compiled
    assert runs[1]["misses"] == 0 and runs[1]["hits"] >= runs[0]["misses"], runs
    assert runs[1]["env"] == runs[0]["env"]
    # and its traced programs are kept (`_program_store`): the second process does not trace the solver again
    assert runs[0]["solver_traces"] >= 1 and runs[0]["stored"] == 1
    assert runs[1]["solver_traces"] == 0, runs


def test_every_program_of_the_package_is_compiled_with_its_compiler_options():
    """hiddenjax's programs go through `hiddenjax._jit` (Triton GEMM tuning off on GPUs), never a bare jit."""
    import re
    from pathlib import Path

    bare = []
    for path in Path(hj.__file__).parent.rglob("*.py"):
        if path.name in ("_jit.py", "_program_store.py"):  # the store compiles with the options `_jit` hands it
            continue
        for number, line in enumerate(path.read_text().splitlines(), 1):
            code = line.split("#")[0]
            if re.search(r"(?<!`)\b(jax\.jit|eqx\.filter_jit)\b(?!`)", code) and not code.strip().startswith(("`", '"')):
                bare.append(f"{path.name}:{number}: {line.strip()}")
    assert not bare, bare
    import jax
    import jaxlib

    from hiddenjax._jit import jit

    # the GPU's Triton GEMM tuning off; on jaxlib 0.10 (where it was measured) the CPU's earlier fusion emitters
    expected = {"xla_gpu_enable_triton_gemm": False}
    if jaxlib.__version__.startswith("0.10."):
        expected["xla_cpu_use_fusion_emitters"] = False
    assert hj.COMPILER_OPTIONS == expected
    # this jaxlib knows every option (a name it does not know fails every program), those of the programs that
    # run long too; each backend ignores the other's
    for runs_long in (False, True):
        assert float(jit(lambda a: a @ a, runs_long=runs_long)(jnp.eye(3))[0, 0]) == 1.0
    assert float(jax.jit(lambda a: a + 1, compiler_options=hj.COMPILER_OPTIONS)(1.0)) == 2.0


def test_a_function_called_inside_another_program_is_traced_once():
    """Inside a caller's trace, hiddenjax's functions are staged without their options (JAX refuses them
    there) and traced once, whether the traced value is an argument or only closed over."""
    import jax

    from hiddenjax._jit import filter_jit, jit

    for wrap in (jit, filter_jit):
        traces = []

        @wrap
        def double(x):
            traces.append(x)
            return 2 * x

        assert float(jax.jit(lambda x: double(x) + 1)(1.0)) == 3.0
        assert len(traces) == 1, (wrap.__name__, len(traces))
        _, ys = jax.lax.scan(lambda c, x: (c, double(x)), 0.0, jnp.arange(3.0))
        assert np.array_equal(np.asarray(ys), [0.0, 2.0, 4.0]) and len(traces) == 2, (wrap.__name__, len(traces))
        # a traced value that is no argument of the call still works (the options are refused, then dropped)
        assert float(jax.jit(lambda x: double(jnp.float32(2.0)) + x)(1.0)) == 5.0
        assert float(double(jnp.float32(3.0))) == 6.0  # at the top level: its own program, with the options


def test_shadow_geometry_calls_are_one_program_each(small_setup):
    """The edge coordinates, the depth lifts and the soft transport compile one program per call, not one
    per array operation (eager, `edge_angle` was 33 programs, `depth_to_points` 12, `Camera.ray_directions`
    11, `SoftTransport.matrix` 13)."""
    import jax.numpy as jnp
    sh = hj.shadows
    s0, s1, light = jnp.array([0.0, 0.31, 0.0]), jnp.array([0.29, 0.31, 0.0]), jnp.array([0.51, 0.9, 0.4])
    assert lowered_programs(lambda: sh.edge_angle(light, s0, s1)) <= 1
    edges = jnp.stack([jnp.stack([s0, s1])] * 3)
    assert lowered_programs(lambda: sh.edge_coordinates(light, edges)) <= 1
    scene, camera = small_setup.scene, small_setup.camera
    depth = hj.depth_map(scene, camera)
    assert lowered_programs(lambda: sh.depth_to_points(depth, camera)) <= 1
    pixels = jnp.array([[3.5, 7.5], [9.5, 1.5]])
    assert lowered_programs(lambda: camera.ray_directions(pixels)) <= 1
    st = sh.SoftTransport.from_scene(scene, camera, hj.EnvGrid(2, 4), samples=1)
    assert lowered_programs(lambda: st.matrix(temperature=321.0)) <= 1


def test_scene_setup_is_transfers_and_a_fit_a_few_programs(small_setup):
    """Building the shadow models from a scene casts host arrays on the host and transfers them (no JAX
    program: `jnp.asarray(x, dtype)` of each array compiled a conversion), a transport matrix's rows become an
    image in one program (five eagerly), and a light fit from a start compiles a handful (`fit_lights` was
    58 with its setup, `hiddenjax design --shape voxels --quick` 174, now 45)."""
    import numpy as np
    sh = hj.shadows
    scene, camera = small_setup.scene, small_setup.camera
    assert lowered_programs(lambda: sh.ShadowScene.from_scene(scene, camera)) <= 1  # the camera's rays
    assert lowered_programs(lambda: sh.SoftTransport.from_scene(scene, camera, hj.EnvGrid(2, 4), samples=1)) <= 1
    triangles = np.concatenate([s.triangles for s in scene])
    assert lowered_programs(lambda: sh.Occluder.from_triangles(triangles)) == 0
    assert lowered_programs(lambda: sh.Receivers.from_points(triangles[:, 0])) == 0
    T = hj.transport_matrix(scene, camera, hj.EnvGrid(2, 4), samples=1, pixel_samples=1)
    column = T.A[:, 0]
    assert lowered_programs(lambda: T.rows_to_image(column)) <= 1
    light = np.array([[0.15, 0.45, 0.1]])
    image = np.asarray(hj.render_point_lights(scene, camera, light, [0.05]))
    fit = lambda: hj.shadows.fit_lights(image, scene, camera, light + [[0.03, 0.0, 0.04]], steps=8, polish=False)
    assert lowered_programs(fit) <= 8
    shadows = sh.ShadowScene.from_scene(scene, camera)
    sh.render_lights(shadows, light, [0.05])
    other = lambda: [sh.render_lights(shadows, light, [0.05], temperature=t, ambient=a) for t in (50.0, 80.0)
                     for a in (0.0, 0.1)]
    assert lowered_programs(other) == 0  # the temperature and the ambient are arguments of one program
    assert lowered_programs(lambda: [sh.light_images(shadows, light, t) for t in (120.0, 240.0)]) <= 1


def test_a_shipped_corner_network_loads_and_tracks_in_a_few_programs():
    """`hj.corners.pretrained` transfers its float16 leaves as float32 arrays cast on the host (one
    conversion program per leaf before: 9), and `track` runs its batches as one program plus the polar
    coordinates' one (the `hiddenjax corner` command compiled 18 programs, now 3)."""
    import numpy as np
    hc = hj.corners
    assert lowered_programs(lambda: hc.pretrained("L", "fixed-lamp")) <= 1
    model = hc.pretrained("L", "fixed-lamp")
    size = hc.pretrained_info("L", "fixed-lamp")["architecture"]["size"]
    frames = np.random.default_rng(0).normal(0.0, 1e-3, (3, size, size)).astype(np.float32)
    assert lowered_programs(lambda: hc.track(model, frames, batch=4)) <= 2


class Shifted(eqx.Module):  # arrays and a static field, as hiddenjax's results
    value: jnp.ndarray
    label: str = eqx.field(static=True)


TRACES = []


def shifted(x, scale, shift, label):
    """A program of arrays (`x`, numpy `scale`), a static number (`shift`) and string; returns `x` itself too."""
    TRACES.append(label)
    return x, Shifted(x * scale + shift, label), jnp.asarray(2.0) * shift, 3


def stored(folder):
    """`shifted` as hiddenjax's own functions are wrapped, with a store in `folder`: a new wrapper is a new process."""
    from hiddenjax import _program_store
    from hiddenjax._jit import filter_jit

    _program_store.enable(folder)
    return filter_jit(shifted)


@pytest.fixture
def program_store(tmp_path):
    from hiddenjax import _program_store

    yield tmp_path / "programs"
    _program_store.enable(None)


def test_a_stored_program_is_not_traced_again_and_returns_what_the_traced_one_does(program_store):
    import jax

    x, scale = jnp.arange(6.0).reshape(2, 3), np.float32(0.5)
    plain = eqx.filter_jit(shifted)(x, scale, 1.5, "a")
    TRACES.clear()
    first = stored(program_store)(x, scale, 1.5, "a")
    assert TRACES == ["a"] and len(list(program_store.iterdir())) == 1  # traced once, kept
    again = stored(program_store)(x, scale, 1.5, "a")  # a new wrapper: nothing in memory, as in a new process
    assert TRACES == ["a"], "the stored program was traced again"
    for out in (first, again):
        assert out[0] is x  # an argument returned as it is stays that array (no copy of an operator's A)
        assert isinstance(stored(program_store)(np.asarray(x), scale, 1.5, "a")[0], jax.Array)  # numpy too, as jit
        assert isinstance(out[1], Shifted) and out[1].label == "a" and out[3] == 3
        assert np.array_equal(out[1].value, plain[1].value) and float(out[2]) == float(plain[2]) == 3.0
        assert jax.typeof(out[2]).weak_type == jax.typeof(plain[2]).weak_type  # weak types as traced
    # another static value or shape is another program; a staged call is part of its caller's program
    stored(program_store)(x, scale, 2.5, "a")
    stored(program_store)(x[:1], scale, 1.5, "a")
    assert TRACES == ["a", "a", "a"] and len(list(program_store.iterdir())) == 3
    assert float(jax.jit(lambda x: stored(program_store)(x, scale, 1.5, "a")[1].value.sum())(x)) == 16.5
    assert len(list(program_store.iterdir())) == 3
    # JAX's settings are part of the key: a float64 argument is float32 without x64, float64 with it
    wide, call = np.arange(3.0), stored(program_store)
    assert call(wide, scale, 1.0, "a")[1].value.dtype == jnp.float32
    with jax.enable_x64():
        assert call(wide, scale, 1.0, "a")[1].value.dtype == jnp.float64
    assert len(list(program_store.iterdir())) == 5


def test_a_damaged_or_unstorable_program_is_traced_as_before(program_store):
    import jax

    x, scale = jnp.arange(3.0), np.float32(2.0)
    stored(program_store)(x, scale, 0.0, "b")
    (entry,) = program_store.iterdir()
    entry.write_bytes(b"half an entry")  # damaged (or from another version of JAX): exported and written again
    TRACES.clear()
    assert np.array_equal(stored(program_store)(x, scale, 0.0, "b")[1].value, [0.0, 2.0, 4.0]) and TRACES == ["b"]
    stored(program_store)(x, scale, 0.0, "b")
    assert TRACES == ["b"]
    # a static argument that does not pickle is not keyed: traced in each process, never stored
    label = lambda: "c"  # noqa: E731
    out = stored(program_store)(x, scale, 1.0, label)
    assert np.array_equal(out[1].value, [1.0, 3.0, 5.0]) and len(list(program_store.iterdir())) == 1
    # a folder that cannot be created: one warning, and the store stays off
    from hiddenjax import _program_store

    a_file = program_store.parent / "file"
    a_file.write_text("x")
    # jax.clear_caches() turns the store off in the process: a later call traces again, as after the clear
    store = stored(program_store)
    jax.clear_caches()
    assert _program_store.folder() is None
    TRACES.clear()
    store(x, scale, 0.0, "b")
    assert TRACES == ["b"]
    with pytest.warns(RuntimeWarning, match="traced programs will not be kept: cannot create"):
        _program_store.enable(a_file / "programs")
    assert _program_store.folder() is None and float(stored(None)(x, scale, 0.0, "b")[2]) == 0.0


def checked(x):
    """A program with a host callback (`eqx.error_if`), which `jax.export` does not serialize."""
    TRACES.append("checked")
    return eqx.error_if(x, x < 0, "negative")


def test_a_program_that_cannot_be_exported_is_marked_and_traced_as_before(program_store, monkeypatch):
    from hiddenjax import _program_store
    from hiddenjax._jit import filter_jit

    exports = []
    monkeypatch.setattr(_program_store, "_export", lambda *a, f=_program_store._export: exports.append(1) or f(*a))
    _program_store.enable(program_store)
    assert float(filter_jit(checked)(jnp.float32(2.0))) == 2.0
    assert [p.suffix for p in program_store.iterdir()] == [".none"] and len(exports) == 1  # tried once on a machine
    assert float(filter_jit(checked)(jnp.float32(3.0))) == 3.0  # a new wrapper: straight to the traced program
    assert len(exports) == 1
    with pytest.raises(Exception, match="negative"):
        filter_jit(checked)(jnp.float32(-1.0))
