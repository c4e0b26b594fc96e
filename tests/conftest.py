import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax
import numpy as np
import pytest

import hiddenjax as hj

jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture
def getkey():
    keys = iter(jax.random.split(jax.random.key(0), 1000))
    return lambda: next(keys)


@pytest.fixture(scope="session")
def small_setup():
    """Teapot on a plane, 48x48 pixels: small enough for many builds per test run."""
    return hj.scenes.object_on_plane("teapot", width=48, height=48)


@pytest.fixture(scope="session")
def plane_only(small_setup):
    """The same camera over the plane alone: nothing can occlude."""
    return hj.Scene([small_setup.scene[0]]), small_setup.camera


def relrmse(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))
