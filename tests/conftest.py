import os
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The suite's own compilation cache, for this process, the CLI's main() run in it and the
# processes it starts: never the user's (a cache file another process is still writing
# reads as a corrupt executable, which aborts XLA).
os.environ.setdefault("SQPARTS_CACHE_DIR", str(Path.home() / ".cache" / "sqparts" / "jax-tests"))

import jax
import numpy as np
import pytest

jax.config.update("jax_compilation_cache_dir", os.environ["SQPARTS_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def random_part_kwargs(rng, *, deform=True, distance=2.0):
    """Random part in front of the camera (numpy kwargs for sqparts.Part)."""
    kw = dict(
        size=rng.uniform(0.08, 0.3, 3),
        squareness=rng.uniform(0.2, 1.8, 2),
        position=np.r_[rng.uniform(-0.1, 0.1, 2), distance],
        orientation=rng.normal(size=3),
    )
    if deform:
        kw["bend"] = rng.uniform(-0.3, 0.3, 2)
        kw["taper"] = rng.uniform(-0.4, 0.4)
    return kw
