"""The first run: numba's path by default, the numpy reference on request, only the kernels a run uses, and one
line on stderr while numba compiles (none when every kernel comes from its cache)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import implicit_cloth as ic
from implicit_cloth.backend import COMPILE_NOTICE

pytest.importorskip("numba")

ROOT = Path(ic.__file__).resolve().parents[1]

#: a small hanging cloth, a few steps, then what was imported and compiled
RUN = """
import json, sys
import implicit_cloth as ic
scene = ic.load_scene(sys.argv[1]).data
scene["cloth"]["resolution"] = [12, 12]
sim = ic.Simulator(scene)
sim.step(3)
out = {"accelerator": sim.run(duration=0.02).report["solver"]["accelerator"],
       "modules": sorted(m for m in sys.modules if m == "numba" or m.startswith("implicit_cloth.kernels"))}
if "numba" in sys.modules:
    from implicit_cloth.kernels import pcg
    names = list(__import__("inspect").signature(pcg.pcg.py_func).parameters)
    out["pcg_cycle_arg"] = [str(sig[-1]) for sig in pcg.pcg.signatures]
    out["pcg_lpar_arg"] = [str(sig[names.index("lpar")]) for sig in pcg.pcg.signatures]
    out["kcycle_signatures"] = len(pcg.kcycle.signatures)
print(json.dumps(out))
"""


def _run(code: str, *args: str, accelerator: str | None = None, **extra_env: str) -> tuple[dict, str]:
    env = {k: v for k, v in os.environ.items() if k != "IMPLICIT_CLOTH_ACCELERATOR"}
    env.update(extra_env, PYTHONPATH=str(ROOT))
    if accelerator is not None:
        env["IMPLICIT_CLOTH_ACCELERATOR"] = accelerator
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1]), p.stderr


def test_default_is_numba_and_a_warm_run_compiles_nothing_and_says_nothing():
    scene = str(ROOT / "examples" / "hanging.toml")
    first, err1 = _run(RUN, scene)                     # compiles what the cache lacks (on a fresh install: all)
    assert err1.count(COMPILE_NOTICE) <= 1, err1
    second, err2 = _run(RUN, scene)                    # everything from the cache now
    assert COMPILE_NOTICE not in err2, err2
    for out in (first, second):
        assert out["accelerator"] == "numba"
        # only the kernels this run uses: no smoothed-prolongation (contact) or strain-limit module, the V-cycle
        # compiled with the K-cycle's branch pruned (its threshold None), so no K-cycle
        assert "implicit_cloth.kernels.smoothed" not in out["modules"]
        assert "implicit_cloth.kernels.strain" not in out["modules"]
        assert out["pcg_cycle_arg"] == ["none"] and out["kcycle_signatures"] == 0, out
        # one thread: the threads' flags None, so that no parallel=True kernel is compiled (kernels.pcg._on)
        assert out["pcg_lpar_arg"] == ["none"], out


def test_numpy_reference_on_request_imports_no_numba():
    out, err = _run(RUN, str(ROOT / "examples" / "hanging.toml"), accelerator="numpy")
    assert out["accelerator"] == "numpy"
    plain = {"implicit_cloth.kernels", "implicit_cloth.kernels.estimate"}      # plain Python, no numba
    assert set(out["modules"]) <= plain, out                                      # numba not even imported
    assert COMPILE_NOTICE not in err


def test_notice_is_said_once_when_numba_compiles():
    """Two compilations (functions no cache holds): the notice once, before them."""
    code = """
import json, sys
from implicit_cloth.backend import get_backend
get_backend("numba")
from numba import njit
f = njit(lambda x: x + 1)
g = njit(lambda x: 2.0 * x)
print("compiling", file=sys.stderr, flush=True)
print(json.dumps([f(1), g(1.5)]))
"""
    out, err = _run(code)
    assert out == [2, 3.0]
    assert err.count(COMPILE_NOTICE) == 1, err
    assert err.index("compiling\n") < err.index(COMPILE_NOTICE)      # said at the compilation, not at import


#: RUN, recording the qualified name of every function numba compiles
RECORDING = RUN.replace("import implicit_cloth as ic\n", """import implicit_cloth as ic
from numba.core import event
compiled = []
class Recorder(event.Listener):
    def on_start(self, ev):
        f = ev.data["dispatcher"].py_func
        compiled.append(f.__module__ + "." + f.__qualname__)
    def on_end(self, ev):
        pass
event.register("numba:compile", Recorder())
""", 1).replace("print(json.dumps(out))", "out['compiled'] = compiled\nprint(json.dumps(out))")


@pytest.mark.slow
def test_a_cold_first_run_compiles_only_the_serial_v_cycle_path(tmp_path):
    """From an empty cache (NUMBA_CACHE_DIR): the notice once, and the hanging cloth on one thread compiles no
    parallel kernel, no K-cycle and no contact kernel (about 20 s of compilation here; those would double it)."""
    out, err = _run(RECORDING, str(ROOT / "examples" / "hanging.toml"), NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    assert err.count(COMPILE_NOTICE) == 1, err
    compiled = set(out["compiled"])
    assert {"implicit_cloth.kernels.pcg.vcycle", "implicit_cloth.kernels.pcg.pcg"} <= compiled
    from implicit_cloth.kernels import assembly, pcg, springs

    parallel = {f"{m.__name__}.{name}" for m in (assembly, pcg, springs) for name, f in vars(m).items()
                if getattr(f, "targetoptions", {}).get("parallel")}
    assert len(parallel) >= 10
    # the spring forces' kernel runs as a parallel region on one thread too, by design (its parallel lowering
    # vectorises the loop: effects.springs), when a line search or an energy check evaluates forces
    parallel.discard("implicit_cloth.kernels.springs.pspring_forces")
    assert not compiled & parallel, sorted(compiled & parallel)
    assert "implicit_cloth.kernels.pcg.kcycle" not in compiled
    assert not [c for c in compiled if c.startswith(("implicit_cloth.kernels.smoothed",
                                                     "implicit_cloth.kernels.strain"))]
