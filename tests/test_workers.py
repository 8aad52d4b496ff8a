"""The effect search's worker pool: every task once, results in order, work shared with the
workers, a dead worker's tasks done here, the caller's torch threads given back; and the search
gives the same model with one process or two."""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import pytest
import torch

from identified.fit.workers import TaskPool, resolve_jobs
from identified.threads import torch_threads

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="workers are forked on Linux only")


def _square(ctx: dict, task: int) -> tuple[int, int]:
    x = torch.linspace(0, 1, 200_000, dtype=torch.float64)  # torch work in every task: a worker's
    assert torch.allclose(x.exp().sum() / x.numel(), torch.tensor(np.e - 1, dtype=torch.float64), rtol=1e-4)
    return ctx["offset"] + task * task, os.getpid()  # OpenMP must run after the fork (no hang)


def _die_in_a_worker(ctx: dict, task: int) -> tuple[int, int]:
    if os.getpid() != ctx["parent"]:
        os._exit(3)  # a worker killed mid-task
    return task + 1, os.getpid()


@linux
def test_tasks_run_once_each_in_order_in_this_process_and_a_worker():
    ctx = {"offset": 1000}
    done = []
    with torch_threads(4):  # this process has run OpenMP threads before the workers are forked
        a = torch.ones(20_000_000)
        assert float((a * 2).sum()) == 4e7
        with TaskPool(_square, ctx, jobs=2) as pool:
            assert torch.get_num_threads() == 1  # one core each while the pool is open
            out = pool.map(list(range(40)), on_done=lambda: done.append(1))
        assert torch.get_num_threads() == 4
    assert [v for v, _ in out] == [1000 + t * t for t in range(40)]
    assert len(done) == 40
    pids = {p for _, p in out}
    assert os.getpid() in pids and len(pids) == 2  # this process takes tasks while the worker is busy


@linux
def test_a_dead_worker_s_tasks_are_done_here_with_a_warning():
    with TaskPool(_die_in_a_worker, {"parent": os.getpid()}, jobs=2) as pool, \
            pytest.warns(RuntimeWarning, match="worker process"):
        out = pool.map(list(range(6)))
    assert [v for v, _ in out] == [t + 1 for t in range(6)]
    assert {p for _, p in out} == {os.getpid()}


def test_one_job_runs_everything_here():
    with TaskPool(_square, {"offset": 0}, jobs=1) as pool:
        out = pool.map([3, 4])
    assert out == [(9, os.getpid()), (16, os.getpid())]


def test_jobs_option():
    assert resolve_jobs(3) == 3 and resolve_jobs(np.int64(2)) == 2
    assert resolve_jobs("auto") >= 1
    for bad in (0, -1, "two", 1.5, True):
        with pytest.raises(ValueError, match="jobs"):
            resolve_jobs(bad)


@linux
@pytest.mark.expensive
def test_the_search_gives_the_same_model_with_one_process_or_two(tmp_path):
    """A hidden drag found the same way, with the same parameters and loop, whatever ``jobs``."""
    from identified.fit.pipeline import fit_model
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import write_model

    clean = tmp_path / "ico.xml"
    write_model(clean, "ico", preset="paper-nonuniform", seed=9)
    plant = tmp_path / "plant.xml"
    plant.write_text(clean.read_text().replace("<option ", '<option viscosity="0.6" '))
    data = collect(plant, CollectConfig(episodes=4, steps=400, seed=31, push_every=100))
    one, two = (fit_model(data, clean, effects="auto", jobs=j) for j in (1, 2))
    assert [e["name"] for e in one.effects] == [e["name"] for e in two.effects] == ["linear_drag"]
    assert [s["added"] for s in one.loop] == [s["added"] for s in two.loop]
    np.testing.assert_allclose(one.stiffness, two.stiffness, rtol=1e-9)
    for a, b in zip(one.effects, two.effects):
        for k in a["parameters"]:
            np.testing.assert_allclose(a["parameters"][k], b["parameters"][k], rtol=1e-9, atol=1e-12)
    for k in ("error_before", "error_after"):
        np.testing.assert_allclose(one.loop[0][k], two.loop[0][k], rtol=1e-6)


def _pool_in_a_daemon(jobs: int) -> list:
    torch.set_num_threads(1)  # forked after this process ran OpenMP threads (see identified.fit.workers)
    with TaskPool(_square, {"offset": 0}, jobs=jobs) as pool:
        return [v for v, _ in pool.map([1, 2, 3])]


@linux
def test_inside_a_multiprocessing_pool_worker_everything_runs_there():
    import multiprocessing

    with multiprocessing.get_context("fork").Pool(1) as outer:  # its workers are daemonic: no children
        assert outer.apply(_pool_in_a_daemon, (2,)) == [1, 4, 9]


def _slow_in_a_worker(ctx: dict, task: int) -> int:
    if os.getpid() != ctx["parent"]:
        time.sleep(60)
        return task
    raise KeyboardInterrupt  # Ctrl-C while this process runs its own task


@linux
def test_ctrl_c_here_stops_the_workers_at_once():
    import multiprocessing

    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt), TaskPool(_slow_in_a_worker, {"parent": os.getpid()}, jobs=2) as pool:
        pool.map([0, 1])  # the worker sleeps on 0, this process is interrupted on 1
    assert time.perf_counter() - t0 < 10  # not the worker's 60 s
    assert multiprocessing.active_children() == []


class _Fake:
    """A stand-in model of the search: its effects' names, the takes it was fitted on and where."""

    def __init__(self, names: tuple[str, ...], takes: int) -> None:
        self.names, self.takes, self.pid = names, takes, os.getpid()
        self.effects = [{"name": n, "parameters": {}} for n in names]
        self.metrics: dict = {}
        self.loop: list = []
        self.source_model = None


#: the held-out errors of the stand-ins: linear drag halves the base model's free run, a constant
#: force beside it does not (nor its one-step error): the search stops after the second round
_SCREEN = {(): 1.0, ("linear_drag",): 0.1, ("constant_force",): 0.8, ("linear_drag", "constant_force"): 0.09}


def _fake_identify(data, topology, effects=(), **kw):
    from identified.fit.regression import IdentifiabilityError

    names = tuple(e.name for e in effects)
    if names not in _SCREEN:
        raise IdentifiabilityError("not a stand-in")
    _FITS.append((names, data.n_episodes))
    return _Fake(names, data.n_episodes)


_FITS: list = []


@linux
@pytest.mark.parametrize("jobs", [1, 2])
def test_the_final_fit_runs_beside_the_last_round_with_two_processes(monkeypatch, jobs):
    """After a round that added an effect, a search in two processes makes the final fit (all the
    takes, the effects chosen so far) beside the next round's candidates; when that round adds
    nothing, it is the model and is not fitted again.  In one process the final fit follows the
    search.  (The real fits' equality with one job or two: the expensive test above.)"""
    from identified import predict
    from identified.fit import checks, pipeline
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import write_model

    monkeypatch.setattr(pipeline, "identify", _fake_identify)
    monkeypatch.setattr(pipeline, "window_error", lambda m, data, steps: _SCREEN[m.names])
    monkeypatch.setattr(pipeline, "_free_run", lambda m, ctx: float("inf") if m is None else _SCREEN[m.names])
    monkeypatch.setattr(pipeline, "one_step_parts", lambda m, data, scheme=None: None)
    monkeypatch.setattr(pipeline, "_one_step_errors", lambda ctx, parts, models: [1.0] * len(parts))
    monkeypatch.setattr(pipeline, "relative_residual", lambda m: 1.0)
    for mod, name in ((checks, "refresh_physics"), (checks, "residual_check"), (predict, "attach_metrics")):
        monkeypatch.setattr(mod, name, lambda *a, **k: None)
    _FITS.clear()
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "ico.xml")
        write_model(path, "ico", preset="paper-uniform")
        data = collect(path, CollectConfig(episodes=4, steps=30, seed=1))
        model = pipeline.fit_model(data, path, effects="auto", jobs=jobs)
    assert model.names == ("linear_drag",) and model.takes == 4
    assert [s["added"] for s in model.loop] == ["linear_drag"]
    finals_here = [f for f in _FITS if f[1] == 4]  # the fits made in this process on all four takes
    if jobs == 1:
        assert finals_here == [(("linear_drag",), 4)]
    else:  # made by the worker (it takes the first, longest task) beside the second round, not here
        assert model.pid != os.getpid() and finals_here == []
