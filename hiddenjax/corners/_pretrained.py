"""Trained localization networks shipped with the package: one per scene class and lighting setting.

Each network is one file in `weights/` (the leaves of a `CornerNet` in float16, equinox leaf
serialisation) and one entry of `weights/manifest.json` that says how to rebuild and reproduce
it: the architecture, the dataset generator's configuration (`generate_dataset`'s `config`, with
the number of scenes used), the training configuration, the package version, the validation
errors (thesis Table 3.1), the learning curve and the file's SHA-256, checked on every load.

Settings (docs/experiments/around-the-corner.md):
- `"fixed-lamp"`: the thesis' rig, one lamp at `FIXED_LAMP` in the corner's frame in every scene;
- `"random-lamp"`: the lamp drawn over the hidden corridor per scene (the harder, more general case).

`examples/train_corner_networks.py` trains and writes them (`save_pretrained`).
"""

import hashlib
import io
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._jit import host_array
from ..io._files import atomic_path
from ._labels import PolarGrid
from ._network import CornerNet
from ._scenes import SCENE_CLASSES

WEIGHTS = Path(__file__).parent / "weights"
SETTINGS = ("fixed-lamp", "random-lamp")
FIXED_LAMP = (0.2, 0.65, 0.15)  # metres, corner frame: the middle of the range the random setting draws from


def setting_lamp(setting: str):
    """The `lamp` argument of `random_corner_scene` / `generate_dataset` for a setting."""
    if setting not in SETTINGS:
        raise ValueError(f"unknown corner setting {setting!r}; choose one of {SETTINGS}")
    return FIXED_LAMP if setting == "fixed-lamp" else None


def _manifest(folder: Path) -> dict:
    path = folder / "manifest.json"
    return json.loads(path.read_text()) if path.exists() else {}


def _name(kind: str, setting: str) -> str:
    return f"{kind}_{setting}"


def _cast(tree, dtype):
    return jax.tree.map(lambda a: a.astype(dtype) if eqx.is_array(a) else a, tree)


def _skeleton(architecture: dict) -> CornerNet:
    """The network's structure with float16 numpy leaves, without running its initialisation (fast)."""
    arch = dict(architecture)
    arch["grid"] = tuple(arch["grid"])
    arch["channels"] = tuple(arch["channels"])
    shapes = eqx.filter_eval_shape(lambda: CornerNet(jax.random.key(0), **arch))
    return jax.tree.map(lambda a: np.zeros(a.shape, np.float16) if isinstance(a, jax.ShapeDtypeStruct) else a, shapes)


def pretrained_info(kind: str, setting: str = "fixed-lamp", *, folder=None) -> dict:
    """The manifest entry of a shipped network (architecture, data, training, validation errors, file)."""
    if kind not in SCENE_CLASSES:
        raise ValueError(f"unknown corner scene class {kind!r}; choose one of {SCENE_CLASSES}")
    setting_lamp(setting)
    folder = Path(folder) if folder is not None else WEIGHTS
    manifest = _manifest(folder)
    entry = manifest.get(_name(kind, setting))
    if entry is None:
        have = ", ".join(sorted(manifest)) or "none"
        raise ValueError(f"no trained network for corner class {kind!r} in setting {setting!r} in {folder} "
                         f"(available: {have}); train one with examples/train_corner_networks.py")
    return entry


def pretrained(kind: str, setting: str = "fixed-lamp", *, folder=None) -> CornerNet:
    """The shipped `CornerNet` for scene class `kind` (`'L'`, `'T'`, `'table'`) and lighting `setting`.

    Its input is a background-subtracted frame of `pretrained_info(...)["architecture"]["size"]`
    pixels a side (`network_frames` resamples other sizes). The file's SHA-256 is checked
    against the manifest; a mismatch is an error, not a silently different network.
    """
    entry = pretrained_info(kind, setting, folder=folder)
    folder = Path(folder) if folder is not None else WEIGHTS
    data = (folder / entry["file"]).read_bytes()
    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise ValueError(f"{folder / entry['file']} does not match its SHA-256 in the manifest: the file is damaged "
                         "or was replaced; reinstall the package or retrain it")
    model = eqx.tree_deserialise_leaves(io.BytesIO(data), _skeleton(entry["architecture"]))
    # float16 leaves cast on the host and transferred: no conversion program per leaf
    return jax.tree.map(lambda a: host_array(a, np.float32) if isinstance(a, np.ndarray) else a, model)


def save_pretrained(folder, model: CornerNet, kind: str, setting: str, architecture: dict, record: dict) -> dict:
    """Write `model` as `{kind}_{setting}.eqx` (float16 leaves) and its manifest entry (`record` + file facts)."""
    setting_lamp(setting)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, _cast(model, jnp.float16))
    data = buffer.getvalue()
    name = _name(kind, setting)
    with atomic_path(folder / f"{name}.eqx") as tmp:
        Path(tmp).write_bytes(data)
    entry = dict(record, kind=kind, setting=setting, file=f"{name}.eqx", bytes=len(data),
                 sha256=hashlib.sha256(data).hexdigest(), architecture=architecture,
                 grid=dict(n_theta=PolarGrid().n_theta, n_rho=PolarGrid().n_rho))
    manifest = _manifest(folder)
    manifest[name] = entry
    with atomic_path(folder / "manifest.json") as tmp:
        Path(tmp).write_text(json.dumps(manifest, indent=1, sort_keys=True, default=_plain) + "\n")
    return entry


def _plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")
