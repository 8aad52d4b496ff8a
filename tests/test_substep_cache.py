"""The compiled substep's cache on disk (tensegrity_gym/backends/substep_cache.py): a second process
loads what the first stored and computes bit for bit the same; a changed constant, changed code or
a damaged entry is never used.

The cheap tests compile a small function in two child processes (a few seconds each); the twin's own
substep, stored by one process and loaded by another, is the expensive test."""

from __future__ import annotations

import ast
import inspect
import json
import os
import pickle
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from tensegrity_gym.backends import substep_cache as sc
from tensegrity_gym.backends.twin_physics import TwinPhysics, compiler_available

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
needs_compiler = pytest.mark.skipif(not compiler_available(), reason="torch.compile needs a C++ compiler")

#: A child process: a small "physics" object whose method is compiled through the cache, for one or
#: more (scale values, offset) settings; prints per setting the cache's answer, whether the result
#: equals a plain torch.compile's bit for bit, and the result itself.
TOY = textwrap.dedent('''
    import json, sys
    import torch
    sys.path.insert(0, sys.argv[1])
    from tensegrity_gym.backends.substep_cache import load_or_compile

    class Toy:
        def __init__(self, scale, offset):
            self.scale = torch.tensor(scale, dtype=torch.float32)  # an input of the compiled code
            self.offset = float(offset)                           # a constant in it

        def step(self, x, y):
            z = torch.sin(x * self.scale + self.offset) * torch.cos(y)
            return z + x, y - 0.5 * z

    out = []
    for scale, offset in json.loads(sys.argv[2]):
        toy = Toy(scale, offset)
        x = torch.linspace(-1, 1, 12).reshape(3, 4)
        y = torch.linspace(0, 2, 12).reshape(3, 4)
        plain = torch.compile(toy.step, dynamic=False)
        fn, status = load_or_compile(Toy.step, toy, (x, y), {}, lambda: plain,
                                     {"scale": toy.scale, "offset": toy.offset})
        a, b, pa, pb = x, y, x, y
        for _ in range(5):
            a, b = fn(a, b)
            pa, pb = plain(pa, pb)
        same = bool(torch.equal(a, pa) and torch.equal(b, pb))
        out.append({"status": status, "same_as_plain": same, "result": a.flatten().tolist()})
    print(json.dumps(out))
''')


def _toy(tmp_path, settings, script="toy.py"):
    path = tmp_path / script
    if not path.exists():
        path.write_text(TOY)
    env = {**os.environ, sc.CACHE_ENV: str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, str(path), ROOT, json.dumps(settings)], capture_output=True, text=True,
                          env=env, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


SCALE = [[1.0, 2.0, 3.0, 4.0]] * 3


@needs_compiler
def test_second_process_hits_and_computes_the_same(tmp_path):
    first = _toy(tmp_path, [[SCALE, 0.25]])
    assert first[0]["status"] == "stored" and first[0]["same_as_plain"]
    entries = os.listdir(tmp_path / "cache")
    assert len(entries) == 1 and entries[0].endswith(".substep")  # no temporary file left

    other_scale = [[0.5, -1.0, 2.0, 0.1]] * 3
    second = _toy(tmp_path, [[SCALE, 0.25], [other_scale, 0.25]])
    # the same call: loaded, and bit for bit what the first process computed
    assert second[0]["status"] == "hit" and second[0]["same_as_plain"]
    assert second[0]["result"] == first[0]["result"]
    # other tensor values: the same compiled code (they are its inputs), still equal to a plain compile
    assert second[1]["status"] == "hit" and second[1]["same_as_plain"]
    assert second[1]["result"] != first[0]["result"]
    assert len(os.listdir(tmp_path / "cache")) == 1


@pytest.mark.expensive
@needs_compiler
def test_changed_constant_or_code_is_compiled_again(tmp_path):
    """~30 s (three child processes that compile); the cheap companions check the key
    (test_key_holds_constants_by_value_and_tensors_by_layout) and the stale entry
    (test_a_damaged_or_stale_entry_is_a_miss) without compiling."""
    first = _toy(tmp_path, [[SCALE, 0.25]])
    # another constant: another key, compiled and stored, never the stored one
    other = _toy(tmp_path, [[SCALE, 0.75]])
    assert other[0]["status"] == "stored" and other[0]["same_as_plain"]
    assert other[0]["result"] != first[0]["result"]
    assert len(os.listdir(tmp_path / "cache")) == 2
    # changed code: the entry of the same key is stale, compiled again and replaced
    (tmp_path / "toy.py").write_text(TOY.replace("y - 0.5 * z", "y - 0.25 * z"))
    changed = _toy(tmp_path, [[SCALE, 0.25]])
    assert changed[0]["status"] == "stored" and changed[0]["same_as_plain"]
    assert changed[0]["result"] != first[0]["result"]  # y's update feeds x's from the second step
    assert len(os.listdir(tmp_path / "cache")) == 2


def _entry(tmp_path):
    key = "0" * 64
    path = tmp_path / f"{key}.substep"
    entry = {"format": sc.FORMAT, "key": key, "torch": torch.__version__,
             "modules": sc._module_hashes(["tensegrity_gym.cables"]), "payload": b"not a compiled function"}
    return key, path, entry


def test_a_damaged_or_stale_entry_is_a_miss(tmp_path):
    key, path, entry = _entry(tmp_path)
    path.write_bytes(pickle.dumps(entry)[:40])  # truncated
    assert sc._read(str(path), key) is None
    stale = {**entry, "modules": {"tensegrity_gym.cables": "0" * 64}}  # the code changed since
    path.write_bytes(pickle.dumps(stale))
    assert sc._read(str(path), key) is None
    path.write_bytes(pickle.dumps(entry))
    assert sc._read(str(path), "1" * 64) is None  # another key's entry
    assert sc._read(str(path), key) is None  # a payload that is not a compiled function


def test_cache_folder_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(sc.CACHE_ENV, str(tmp_path))
    assert sc.cache_dir() == str(tmp_path)
    for off in ("0", "off"):
        monkeypatch.setenv(sc.CACHE_ENV, off)
        assert sc.cache_dir() is None
        fn, status = sc.load_or_compile(TwinPhysics._eager_substep, None, (), {}, lambda: "plain", {})
        assert (fn, status) == ("plain", "off")
    monkeypatch.delenv(sc.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert sc.cache_dir() == os.path.join(str(tmp_path), "tensegrity-gym", "twin-substep")


def test_key_holds_constants_by_value_and_tensors_by_layout():
    class Obj:
        def __init__(self, dt, w):
            self.dt, self.w = dt, w

    class Addressed:  # its repr holds its address: the key must not depend on it
        pass

    def key(*inputs):
        return sc.call_key(TwinPhysics._eager_substep, inputs, {"cpp_wrapper": True})

    base = key(Obj(0.001, torch.ones(3)))
    assert key(Obj(0.001, torch.full((3,), 7.0))) == base  # tensor values: inputs, not the key
    assert key(Obj(0.002, torch.ones(3))) != base  # a constant
    assert key(Obj(0.001, torch.ones(4))) != base  # a shape
    assert key(Obj(0.001, torch.ones(3, dtype=torch.float64))) != base  # a dtype
    assert key(Obj(0.001, None)) != base  # an optional part missing
    assert sc.call_key(TwinPhysics._eager_substep, (Obj(0.001, torch.ones(3)),), {}) != base  # options
    # every part is walked, also where a walked object's id is free again (no false "seen")
    assert key(Obj(Obj(0.001, None), Obj(0.002, None))) != key(Obj(Obj(0.001, None), Obj(0.003, None)))
    d1 = {Addressed(): 1.0, Addressed(): 2.0}
    d2 = {Addressed(): 1.0, Addressed(): 2.0}
    assert key(d1) == key(d2)


def test_twins_of_one_model_share_one_key():
    """Identical twins built one after the other (objects at other addresses, ids freed and reused
    while the key is computed) get one key; another time step is another key."""
    import gymnasium as gym

    from tensegrity_gym.backends.twin_physics import _split

    def key(ph):
        args = (_split(ph.state), ph.rest, ph.rest_act, ph.target, None, None)
        return sc.call_key(TwinPhysics._eager_substep, (ph._substep_reads(), *args), ph._inductor_options())

    def twin():
        return gym.make_vec("TensegrityIco-v0", num_envs=4, vectorization_mode="vector_entry_point",
                            backend="identified").physics

    twins = [twin() for _ in range(3)]
    keys = {key(ph) for ph in twins for _ in range(3)}
    assert len(keys) == 1
    ph = twin()
    ph.engine.dt *= 2
    assert key(ph) not in keys


def test_substep_reads_list_every_attribute_the_substep_reads():
    """The key fingerprints :meth:`TwinPhysics._substep_reads`; it must name every ``self.x`` the
    substep reads, or a constant could change without changing the key."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(TwinPhysics._eager_substep)))
    read = {n.attr for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name) and n.value.id == "self"}
    names = set(ast.literal_eval(ast.parse(textwrap.dedent(inspect.getsource(TwinPhysics._substep_reads)))
                                 .body[0].body[-1].value.generators[0].iter))
    assert read == names


TWIN = textwrap.dedent('''
    import json, sys
    import numpy as np
    sys.path.insert(0, sys.argv[1])
    import gymnasium as gym
    import tensegrity_gym  # noqa: F401
    from tensegrity_gym.backends.twin_physics import TwinPhysics

    venv = gym.make_vec("TensegrityIco-v0", num_envs=4, vectorization_mode="vector_entry_point",
                        backend="identified", backend_kwargs={"compile": True})
    obs, _ = venv.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs, *_ = venv.step(rng.uniform(-1, 1, (4,) + venv.single_action_space.shape).astype(np.float32))
    ph = venv.physics
    print(json.dumps({"status": ph.cache_status, "obs": obs.tolist(),
                      "pos": ph.states_numpy()[0].tolist()}))
''')


@pytest.mark.expensive
@needs_compiler
def test_twin_substep_loaded_by_a_second_process_steps_bit_identically(tmp_path):
    """The twin's own substep: one process compiles and stores it, a second loads it and steps the
    same envs from the same seeds to the same bits (~1 min: one full compilation)."""
    script = tmp_path / "twin.py"
    script.write_text(TWIN)
    env = {**os.environ, sc.CACHE_ENV: str(tmp_path / "cache"), "TENSEGRITY_TWIN_COMPILE": "1"}
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, str(script), ROOT], capture_output=True, text=True, env=env,
                              timeout=600, check=False)
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    assert [r["status"] for r in runs] == ["stored", "hit"]
    np.testing.assert_array_equal(np.array(runs[1]["obs"]), np.array(runs[0]["obs"]))
    np.testing.assert_array_equal(np.array(runs[1]["pos"]), np.array(runs[0]["pos"]))


ISA = textwrap.dedent('''
    import sys
    import torch  # noqa: F401
    sys.path.insert(0, sys.argv[1])
    from tensegrity_gym.backends import substep_cache as sc
    if sys.argv[2] == "prefetch":
        sc.prefetch()
        for thread in sc._PREFETCH:
            thread.join()
    from torch._inductor import cpu_vec_isa as c
    print(repr([(str(i), getattr(i, "_is_avx512_bf16_supported", None), i.build_arch_flags())
                for i in c.valid_vec_isa_list()] + [str(c.pick_vec_isa())]))
''')


@pytest.mark.expensive  # 11-13 s: two fresh processes importing inductor
@needs_compiler
def test_prefetch_finds_the_instruction_sets_inductor_finds(tmp_path):
    """The prefetch probes the instruction sets side by side; the compiled code's flags must be
    those inductor's own pass, one by one, would choose."""
    script = tmp_path / "isa.py"
    script.write_text(ISA)
    env = {**os.environ, sc.CACHE_ENV: str(tmp_path / "cache")}
    out = [subprocess.run([sys.executable, str(script), ROOT, mode], capture_output=True, text=True, env=env,
                          timeout=300, check=True).stdout.strip().splitlines()[-1] for mode in ("prefetch", "plain")]
    assert out[0] == out[1]
