import os
import re
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The suite's own compilation cache, for this process, the CLI's main() run in it and the
# processes it starts: never the user's (a cache file another process is still writing
# reads as a corrupt executable, which aborts XLA).
# pytest-xdist's workers share it: with a size bound, as the command line sets it, JAX reads
# and writes every entry under a file lock, so no worker reads an entry half-written.
os.environ.setdefault("SQPARTS_CACHE_DIR", str(Path.home() / ".cache" / "sqparts" / "jax-tests"))

import jax
import numpy as np
import pytest

from sqparts._compile import CACHE_MAX_BYTES

# Also through the environment, which the processes tests start (the notebooks' kernels)
# read when they import JAX.
os.environ.update(
    JAX_COMPILATION_CACHE_DIR=os.environ["SQPARTS_CACHE_DIR"],
    JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1.0",
    JAX_COMPILATION_CACHE_MAX_SIZE=str(CACHE_MAX_BYTES),
)
jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)
jax.config.update("jax_compilation_cache_dir", os.environ["SQPARTS_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def release_crowded_programs():
    """After each test, the compiled programs are dropped once the process holds a quarter
    of the kernel's memory-mapping limit: the suite compiles thousands of programs in one
    process, and at the limit the next compilation aborts inside LLVM."""
    yield
    from sqparts._compile import release_if_crowded

    release_if_crowded(fraction=0.25)


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


# --- the command line -----------------------------------------------------------------

ERROR_STYLE = re.compile(r"^sqparts: error: \S.*?: got .+, expected .+$")


def cli_error(capsys, argv) -> str:
    """Run ``sqparts ARGV`` in this process; it must exit 2 with one error line in the
    project's style (no traceback). Returns the line."""
    from sqparts.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert ERROR_STYLE.match(err), err
    return err


def no_staging_left(folder: Path) -> bool:
    """No temporary sibling folder of an output is left under ``folder``."""
    return not list(Path(folder).rglob(".sqparts-*"))


def spawn_cli(argv, *, ignore_sigint=False) -> subprocess.Popen:
    """``python -m sqparts ARGV`` in a new process (text pipes). ``ignore_sigint`` starts it
    with SIGINT ignored, as a shell starts a background job, so the interpreter installs no
    handler of its own and the first one is the CLI's (the shell's way: no ``preexec_fn``,
    since forking a process that runs JAX may deadlock)."""
    code = (
        "import runpy, sys\nsys.argv = ['sqparts', *sys.argv[1:]]\nrunpy.run_module('sqparts', run_name='__main__')\n"
    )
    command = [sys.executable, "-c", code, *argv]
    if ignore_sigint:
        command = ["sh", "-c", 'trap "" INT; exec "$0" "$@"', *command]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
