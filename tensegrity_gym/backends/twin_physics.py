"""The twin's physics: N copies of an identified spring-rod system with cable motors, stepped together.

:class:`TwinPhysics` holds the state tensors ``(*B, R, ·)`` (``B = (N,)`` batched, ``()`` single)
and advances them: every physics substep is the cable motors (:func:`tensegrity_gym.cables.motor_step`,
the plant's motor model on tensors) then ONE engine step (:meth:`identified.engine.SpringRodEngine.step`,
with whatever effects the engine was built with) for all N copies. The single twin env
(:class:`~tensegrity_gym.backends.identified_backend.IdentifiedBackend`) and the batched one
(:class:`~tensegrity_gym.envs.vector.TensegrityIcoVectorEnv`) both step through it.

Speed, two policies, each a keyword argument with a default that suits a CPU:

* **Threads** (``num_threads``, default ``"auto"``): torch's intra-op threads spin while they wait
  for work; on a machine where another process holds a core they fight it, and the batched twin
  at 256 envs fell from ~4,000 to ~120 env steps/s with torch's 2 threads on 2 cores
  (``benchmarks/bench_twin.py`` measures it). ``"auto"`` runs the twin's CPU work on ONE thread,
  which is never slower under load and, measured, as fast or faster on a quiet machine at the
  batch sizes that fit a CPU; an int asks for that many threads; ``None`` leaves torch's setting.
  The setting is scoped: :func:`torch_threads` sets it for the twin's step and puts the caller's
  value back after, so the user's global ``torch.set_num_threads`` is never changed behind their
  back (torch's thread count is process-wide: another Python thread running torch work during
  the twin's step sees the twin's count). CUDA work is not affected.
* **Compilation** (``compile``, default ``"auto"``): one substep (motors + engine step) is compiled
  once with ``torch.compile`` (inductor: the substep's hundreds of small kernels become a few fused
  loops), on CPU and CUDA alike; a substep function, not an unrolled rollout, so it compiles once
  (timed in :attr:`TwinPhysics.compile_seconds`). The compiled substep is kept in a cache on disk
  (:mod:`tensegrity_gym.backends.substep_cache`, keyed by the model's structure and constants, the
  shapes and the code): the first process that steps a model compiles it ahead of time and stores
  it (31-60 s on 2 cores at load 3-4 with ground_contact, 100-140 s with pyramid_contact), the next
  ones load it (the first step 0.24-0.29 s, 3-4 s with inductor's imports while the env is built, on 2 cores at load 3-6, against 8-11 s for a
  plain ``torch.compile`` served from inductor's own cache; :attr:`TwinPhysics.cache_status` says
  which). ``TENSEGRITY_TWIN_CACHE=0`` turns the cache off (a plain ``torch.compile``). The
  substep steps the state's *components* (:meth:`identified.engine.SpringRodEngine.step_components`:
  one (*B, R) tensor per coordinate, no trailing dimension of 3), which inductor vectorises across
  rods and envs; an engine that is not :attr:`~identified.engine.SpringRodEngine.fused` (an effect
  without a component form, another integrator) steps through ``SpringRodEngine.step``. On a CPU
  the single twin's compiled substep has inductor's C++ wrapper (:meth:`TwinPhysics._inductor_options`). ``"auto"`` compiles when a C++ compiler is on
  the PATH and the environment variable ``TENSEGRITY_TWIN_COMPILE`` is not ``0``, else runs eagerly
  (without a compiler it says so once a process: the eager twin is many times slower); a compilation that fails
  warns once and falls back to eager. ``True``/``False`` force it. The compiled and the eager
  substeps agree to rounding (tests/test_twin_speed.py).

MuJoCo tendon actuators (``actuators``, an :class:`identified.engine.actuators.ActuatorBank` of the
identified model's): every substep their force on the tendons (gain times activation plus bias)
goes into the engine step (``tendon_force``) and their activations then follow the held commands
(:meth:`TwinPhysics.set_ctrl`) as MuJoCo's Euler integrator steps them.

Divergence: a copy whose state stops being finite is marked (:attr:`TwinPhysics.diverged`) and
reads as NaN until it is reset.
"""

from __future__ import annotations

import copy
import os
import shutil
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from identified.engine import SpringRodEngine, SpringRodParams
from identified.engine.actuators import ActuatorBank
from identified.state import RodState
from identified.threads import torch_threads
from tensegrity_gym.backends.substep_cache import load_or_compile, prefetch
from tensegrity_gym.cables import MotorSpec, motor_step

__all__ = ["COMPILE_ENV", "TwinPhysics", "compiler_available", "resolve_threads", "torch_threads"]

#: Environment variable: ``0`` turns the ``compile="auto"`` default off (eager twin).
COMPILE_ENV = "TENSEGRITY_TWIN_COMPILE"


def compiler_available() -> bool:
    """True when a C++ compiler that inductor can use is on the PATH (``$CXX``, g++, c++, clang++)."""
    names = [os.environ.get("CXX", ""), "g++", "c++", "clang++"]
    return any(n and shutil.which(n) for n in names)


def resolve_threads(num_threads: int | str | None, device: torch.device) -> int | None:
    """The intra-op thread count the twin runs under: ``"auto"`` -> 1 on CPU (``None`` on other
    devices: nothing to set); an int >= 1 as given; ``None``: leave torch's setting."""
    if num_threads is None:
        return None
    if num_threads == "auto":
        return 1 if device.type == "cpu" else None
    if isinstance(num_threads, bool) or not isinstance(num_threads, (int, np.integer)) or num_threads < 1:
        raise ValueError(f"num_threads must be 'auto', None or an integer >= 1, got {num_threads!r}")
    return int(num_threads)


#: said once a process: the twin on a CPU without a compiler
_EAGER_WARNING = ("no C++ compiler on the PATH (g++, c++, clang++ or $CXX): the twin runs eagerly, many times "
                  "slower than compiled (its exact contact law: ~19 ms a physics step of 8 envs, against ~1.2 ms "
                  "of 64 compiled); install one to train fast, or set TENSEGRITY_TWIN_COMPILE=0 to run eagerly "
                  "without this warning")
_warned_eager = False


def _wants_compile(compile: bool | str, device: torch.device) -> bool:
    global _warned_eager
    if compile == "auto":
        if os.environ.get(COMPILE_ENV, "1").strip() in ("0", "false", "no", "off"):
            return False
        if device.type != "cpu":
            return True
        if not compiler_available():
            if not _warned_eager:
                warnings.warn(_EAGER_WARNING, RuntimeWarning, stacklevel=3)
                _warned_eager = True
            return False
        return True
    if not isinstance(compile, bool):
        raise ValueError(f"compile must be 'auto', True or False, got {compile!r}")  # noqa: TRY004
    return compile


class TwinPhysics:
    """N copies of an identified spring-rod system with cable motors, stepped together.

    State tensors have shape ``(*B, R, ·)`` with ``B = (N,)`` (``batch=N``) or ``()``
    (``batch=None``); rest lengths ``(*B, S)``; motor targets ``(*B, A)``. One :meth:`step` runs
    ``n_substeps`` times: motors, then ONE batched engine step.

    Args:
        engine: the identified engine (its dtype and device are used throughout).
        motor: the motor specification; ``actuated_index`` (A,) the springs it drives.
        batch: number of copies N, or ``None`` for one unbatched system.
        chunk_size: ``None`` (default): one engine call per substep for all N copies. An int: the
            copies are stepped in consecutive blocks of this many, each block through all its
            substeps (the copies are independent: the same result up to rounding).
        num_threads: torch intra-op threads for the twin's work, ``"auto"`` (1 on CPU), an int,
            or ``None`` (torch's setting); scoped to :meth:`step` (module docstring).
        compile: ``"auto"``, ``True`` or ``False``: ``torch.compile`` one substep (module docstring).
        per_env: each copy carries its own parameters (needs ``batch``, not ``chunk_size``): the
            engine's spring and rod parameters get a leading (N,) dimension, the effects with a
            component form (ground contact) their parameters as (N, 1, P), and every copy a rest
            offset per spring and a motor speed; all start at the engine's values and change with
            :meth:`set_parameters`. The engine is copied: the one passed in is left as it is.
        actuators: the identified MuJoCo tendon actuators (module docstring), ``None``: none.
    """

    def __init__(self, engine: SpringRodEngine, motor: MotorSpec, actuated_index: np.ndarray,
                 batch: int | None = None, chunk_size: int | None = None,
                 num_threads: int | str | None = "auto", compile: bool | str = "auto",
                 per_env: bool = False, actuators: ActuatorBank | None = None) -> None:
        if batch is not None and (int(batch) != batch or batch < 1):
            raise ValueError(f"batch must be an integer >= 1 or None, got {batch}")
        if chunk_size is not None and (int(chunk_size) != chunk_size or chunk_size < 1 or batch is None):
            raise ValueError(f"chunk_size must be an integer >= 1 (and needs batch), got {chunk_size}")
        self.chunk_size = None if chunk_size is None or chunk_size >= (batch or 0) else int(chunk_size)
        if per_env and (batch is None or self.chunk_size is not None):
            raise ValueError("per_env parameters need a batch and no chunk_size")
        self.per_env = bool(per_env)
        #: per-copy parameters: the rest offsets (N, S) added to the springs' rest lengths and the
        #: motor speed (N, 1) (a float when not per copy)
        self._rest_offset: torch.Tensor | None = None
        self._speed: Any = motor.speed
        if per_env:
            engine = self._per_env_engine(engine, int(batch))  # type: ignore[arg-type]
            self._rest_offset = torch.zeros((int(batch), engine.n_springs), dtype=engine.dtype, device=engine.device)
            self._speed = torch.full((int(batch), 1), float(motor.speed), dtype=engine.dtype, device=engine.device)
        self.engine = engine
        self.motor = motor
        self.batch = None if batch is None else int(batch)
        self.shape: tuple[int, ...] = () if batch is None else (int(batch),)
        dt, dev = engine.dtype, engine.device
        self.num_threads = resolve_threads(num_threads, dev)
        self.compiled = _wants_compile(compile, dev)
        #: seconds spent compiling the substep (first step; 0 when eager)
        self.compile_seconds = 0.0
        #: where the compiled substep came from (:func:`~tensegrity_gym.backends.substep_cache.load_or_compile`):
        #: ``"hit"`` (the cache on disk), ``"stored"`` (compiled and stored), ``"off"``/``"failed"``/
        #: ``"unsaved"`` (compiled in this process only); ``None`` before the first compiled step
        self.cache_status: str | None = None
        self._act = torch.as_tensor(np.asarray(actuated_index, dtype=np.int64), device=dev)
        self._all_actuated = bool(np.array_equal(np.asarray(actuated_index), np.arange(engine.n_springs)))
        self._lo = torch.as_tensor(motor.rest_min, dtype=dt, device=dev)
        self._hi = torch.as_tensor(motor.rest_max, dtype=dt, device=dev)
        R, S = engine.n_rods, engine.n_springs
        z3 = torch.zeros(self.shape + (R, 3), dtype=dt, device=dev)
        quat = torch.zeros(self.shape + (R, 4), dtype=dt, device=dev)
        quat[..., 0] = 1.0
        self.state = RodState(z3, quat, z3.clone(), z3.clone())
        self.rest = torch.ones(self.shape + (S,), dtype=dt, device=dev)  # every spring, (*B, S)
        self.rest_act = self.rest[..., self._act].clone()  # the motors' state, (*B, A)
        self.target = self.rest_act.clone()
        self.diverged = torch.zeros(self.shape, dtype=torch.bool, device=dev)
        self.actuators = actuators if actuators is not None and actuators.n else None
        U = 0 if self.actuators is None else self.actuators.n
        self.ctrl = torch.zeros(self.shape + (U,), dtype=dt, device=dev)  # held commands (*B, U)
        self.act = torch.zeros(self.shape + (U,), dtype=dt, device=dev)  # activations (*B, U)
        self._substep: Callable[..., tuple[torch.Tensor, ...]] = self._eager_substep
        self._compiled_substep: Callable[..., tuple[torch.Tensor, ...]] | None = None
        self._first_call = True
        self._fused = engine.fused
        if self.compiled and dev.type == "cpu":
            prefetch()

    # ------------------------------------------------------------------ conversions
    def tensor(self, x: Any) -> torch.Tensor:
        """``x`` as a tensor of the engine's dtype and device."""
        e = self.engine
        if isinstance(x, torch.Tensor):
            return x.to(dtype=e.dtype, device=e.device)
        return torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=e.dtype, device=e.device)

    def _index(self, index: Any) -> Any:
        """Batch index: ``None`` = every copy (``...``), else an int array/tensor of copies."""
        if index is None:
            return ...
        if self.batch is None:
            raise ValueError("an unbatched TwinPhysics takes index=None")
        return torch.as_tensor(np.asarray(index, dtype=np.int64), device=self.engine.device)

    # ------------------------------------------------------------------ reset and step
    def reset(self, pos: Any, quat: Any, vel: Any, angvel: Any, rest: Any, index: Any = None) -> None:
        """Put the copies ``index`` (``None``: all) at the given states and rest lengths (S,) each;
        their motor targets become their actuated rest lengths, and they are no longer diverged."""
        i = self._index(index)
        for field, value in zip(self.state, (pos, quat, vel, angvel), strict=True):
            field[i] = self.tensor(value)
        self.rest[i] = self.tensor(rest)
        ra = self.rest[i][..., self._act]
        self.rest_act[i] = ra
        self.target[i] = ra
        self.ctrl[i] = 0.0  # as mj_resetData: no command, activations at rest
        self.act[i] = 0.0
        self.diverged[i] = False

    def set_ctrl(self, ctrl: Any, index: Any = None) -> None:
        """The actuators' commands (*B, U), held until changed."""
        self.ctrl[self._index(index)] = self.tensor(ctrl)

    def actuator_state_numpy(self) -> np.ndarray:
        """(*B, U) what each actuator's force acts on now: its activation, or its command where it
        has no dynamics."""
        a = self.act if self.actuators is None else torch.where(self.actuators.direct, self.ctrl, self.act)
        return a.detach().to("cpu", torch.float64, copy=True).numpy()

    def set_targets(self, target: Any, index: Any = None) -> None:
        """Motor targets (*B, A) in metres (clipped into the motor bounds)."""
        t = self.tensor(target)
        self.target[self._index(index)] = torch.minimum(torch.maximum(t, self._lo), self._hi)

    # ------------------------------------------------------------------ per-copy parameters
    @staticmethod
    def _per_env_engine(engine: SpringRodEngine, n: int) -> SpringRodEngine:
        """A copy of ``engine`` whose parameters have a leading (n,) dimension (values unchanged)."""
        e = copy.copy(engine)
        p = engine.params
        e.params = SpringRodParams(**{k: v.detach().expand((n,) + tuple(v.shape)).clone()
                                      for k, v in p.as_dict().items()})
        e.effects = []
        for eff in engine.effects:
            eff = copy.copy(eff)
            if hasattr(eff, "wrench_components") and getattr(eff, "values", None) is not None:
                th = torch.as_tensor(np.asarray(eff.values, dtype=np.float64), dtype=engine.dtype, device=engine.device)
                eff.bind(th.expand(n, 1, th.shape[-1]).clone())  # a copy's bind leaves the original's cache
            e.effects.append(eff)
        return e

    def effect_parameters(self) -> dict[str, torch.Tensor]:
        """The per-copy parameters of each effect that has them, (N, 1, P) (``per_env`` only)."""
        out = {}
        for eff in self.engine.effects:
            th = eff._cache.get(("theta", self.engine.dtype, self.engine.device)) if hasattr(eff, "_cache") else None
            if th is not None and th.dim() == 3:
                out[eff.name] = th
        return out

    def set_parameters(self, index: Any, *, stiffness: Any = None, damping: Any = None, mass: Any = None,
                       inertia: Any = None, rest_offset: Any = None, motor_speed: Any = None,
                       effects: dict[str, Any] | None = None) -> None:
        """Give the copies ``index`` (n,) their own parameters (``per_env`` only; ``None`` keeps a
        parameter as it is): ``stiffness``, ``damping``, ``rest_offset`` (n, S) (N/m, N s/m, m, the
        offset added to every spring's rest length), ``mass`` (n, R) kg, ``inertia`` (n, R, 3)
        kg m², ``motor_speed`` (n,) m/s, ``effects`` {name: (n, P)} in the effect's parameter order.
        Written in place: a compiled substep reads the new values."""
        if not self.per_env:
            raise ValueError("set_parameters needs a TwinPhysics built with per_env=True")
        i = self._index(index)
        p = self.engine.params
        for name, value in (("stiffness", stiffness), ("damping", damping), ("mass", mass), ("inertia", inertia)):
            if value is not None:
                getattr(p, name)[i] = self.tensor(value)
        if rest_offset is not None:
            self._rest_offset[i] = self.tensor(rest_offset)  # type: ignore[index]
        if motor_speed is not None:
            self._speed[i] = self.tensor(motor_speed).reshape(-1, 1)
        table = self.effect_parameters()
        for name, value in (effects or {}).items():
            if name not in table:
                raise ValueError(f"effect '{name}' has no per-copy parameters (per-copy: {sorted(table) or 'none'})")
            table[name][i] = self.tensor(value).reshape(-1, 1, table[name].shape[-1])

    def step(self, n_substeps: int, push_force: Any | None = None, push_point: Any | None = None) -> None:
        """``n_substeps`` physics steps of every copy, the push (``(*B, R, 3)`` world force, N, at
        ``(*B, R, 3)`` rod-frame points, m) held throughout."""
        pf = None if push_force is None else self.tensor(push_force)
        pp = None if push_point is None else self.tensor(push_point)
        c, n = self.chunk_size, int(n_substeps)
        acts = self.actuators is not None
        with torch_threads(self.num_threads), torch.no_grad():
            if c is None:
                state, rest, rest_act, act = self._advance(n, self.state, self.rest, self.rest_act, self.target, pf,
                                                           pp, self.act if acts else None, self.ctrl)
            else:
                parts = []
                for a in range(0, self.batch, c):  # type: ignore[arg-type]
                    sl = slice(a, a + c)
                    block = RodState(*(x[sl] for x in self.state))
                    parts.append(self._advance(n, block, self.rest[sl], self.rest_act[sl], self.target[sl],
                                               None if pf is None else pf[sl], None if pp is None else pp[sl],
                                               self.act[sl] if acts else None, self.ctrl[sl]))
                state = RodState(*(torch.cat([p[0][k] for p in parts]) for k in range(4)))
                rest = torch.cat([p[1] for p in parts])
                rest_act = torch.cat([p[2] for p in parts])
                act = torch.cat([p[3] for p in parts]) if acts else None
            finite = torch.isfinite(torch.cat(tuple(state), dim=-1)).flatten(-2).all(-1)
        if act is not None:
            self.act = act
        self.state = state
        self.rest = rest.clone() if rest is rest_act else rest  # two tensors: reset writes both
        self.rest_act = rest_act
        self.diverged = self.diverged | ~finite

    def _advance(self, n: int, state: RodState, rest: torch.Tensor, rest_act: torch.Tensor,
                 target: torch.Tensor, pf: torch.Tensor | None, pp: torch.Tensor | None,
                 act: torch.Tensor | None = None, ctrl: torch.Tensor | None = None
                 ) -> tuple[RodState, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``n`` substeps (motors, then one engine step) of a block of copies. The substeps work on
        the state's components (:mod:`identified.engine.smallmat`: one contiguous tensor (*B, R)
        per coordinate), split once before and stacked once after. ``act``/``ctrl``: the block's
        actuator activations and commands (``act`` ``None``: no actuators)."""
        comps = _split(state)
        if self._first_call:
            self._first_call = False
            if self.compiled:
                return self._compile_and_advance(n, comps, rest, rest_act, target, pf, pp, act, ctrl)
        sub = self._substep
        x, r, ra, a = comps, rest, rest_act, act
        try:
            for _ in range(n):
                if act is None:
                    x, r, ra = sub(x, r, ra, target, pf, pp)
                else:
                    x, r, ra, a = sub(x, r, ra, target, pf, pp, a, ctrl)
        except Exception as exc:
            if sub is self._eager_substep:
                raise
            # a later compilation (a push, a new block shape) failed: eager from the same inputs
            self._fall_back(exc)
            return self._advance(n, state, rest, rest_act, target, pf, pp, act, ctrl)
        return _stack(x), r, ra, a

    def _fall_back(self, exc: Exception) -> None:
        """Stop compiling (warn once) and step eagerly from now on."""
        self.compiled = False
        self._substep = self._eager_substep
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        warnings.warn(f"torch.compile of the twin's substep failed ({type(exc).__name__}: {msg}); the twin "
                      "runs eagerly (compile=False silences this)", stacklevel=5)

    def _eager_substep(self, state: tuple, rest: torch.Tensor, rest_act: torch.Tensor, target: torch.Tensor,
                       pf: torch.Tensor | None, pp: torch.Tensor | None, act: torch.Tensor | None = None,
                       ctrl: torch.Tensor | None = None) -> tuple:
        """One substep: the motors move the actuated rest lengths, then one engine step
        (:meth:`~identified.engine.SpringRodEngine.step_components` when the engine is fused, else
        :meth:`~identified.engine.SpringRodEngine.step` on the stacked state) with the actuators'
        tendon forces, then the actuators' activations follow ``ctrl``. ``state`` and the result:
        the components of (pos, quat, vel, angvel), each (*B, R); with ``act`` the result ends
        with the new activations."""
        e = self.engine
        if self.motor.n:
            rest_act = motor_step(rest_act, target, self._speed, e.dt, self._lo, self._hi)
            rest = rest_act if self._all_actuated else rest.index_copy(-1, self._act, rest_act)
        springs = rest if self._rest_offset is None else rest + self._rest_offset
        force = None if act is None else self.actuators.force(ctrl, act)  # type: ignore[union-attr]
        if self._fused:
            x = e.step_components(*state, springs, pf, pp, force)
        else:
            x = _split(e.step(_stack(state), springs, pf, pp, force))
        if act is None:
            return x, rest, rest_act
        return x, rest, rest_act, self.actuators.step(ctrl, act)  # type: ignore[union-attr]

    def _compile_and_advance(self, n: int, comps: tuple, rest: torch.Tensor, rest_act: torch.Tensor,
                             target: torch.Tensor, pf: torch.Tensor | None, pp: torch.Tensor | None,
                             act: torch.Tensor | None = None, ctrl: torch.Tensor | None = None
                             ) -> tuple[RodState, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The first step with ``compile``: compile the substep (timed), check it runs, keep it;
        on any failure warn once and stay eager."""
        extra = () if act is None else (act, ctrl)
        # one eager substep first: effects fill their lazy caches (geometry, parameter tensors)
        # eagerly, so the compiled substep reads them as constants and stays ONE graph (a cache
        # filled inside the traced call is numpy work that breaks the graph)
        self._eager_substep(comps, rest, rest_act, target, pf, pp, *extra)
        t0 = time.perf_counter()
        args = (comps, rest, rest_act, target, pf, pp, *extra)
        try:
            options = self._inductor_options()

            def plain() -> Callable[..., tuple]:
                return torch.compile(self._eager_substep, dynamic=False, options=options)

            fn, self.cache_status = load_or_compile(TwinPhysics._eager_substep, self, args, options, plain,
                                                    self._substep_reads())
            out = fn(*args)
        except Exception as exc:  # noqa: BLE001 - inductor raises assorted types (no compiler, codegen)
            self._fall_back(exc)
            return self._advance(n, _stack(comps), rest, rest_act, target, pf, pp, act, ctrl)
        self.compile_seconds = time.perf_counter() - t0
        self._substep = self._compiled_substep = fn
        x, rest, rest_act, a = (*out, None) if act is None else out
        for _ in range(n - 1):
            if act is None:
                x, rest, rest_act = fn(x, rest, rest_act, target, pf, pp)
            else:
                x, rest, rest_act, a = fn(x, rest, rest_act, target, pf, pp, a, ctrl)
        return _stack(x), rest, rest_act, a

    def _substep_reads(self) -> dict[str, Any]:
        """The attributes :meth:`_eager_substep` reads: what shapes its compiled code besides its
        arguments (the key of :func:`~tensegrity_gym.backends.substep_cache.load_or_compile`)."""
        return {k: getattr(self, k) for k in ("engine", "motor", "actuators", "_speed", "_lo", "_hi", "_act",
                                              "_all_actuated", "_rest_offset", "_fused")}

    def _inductor_options(self) -> dict[str, Any]:
        """Inductor settings for the substep. The single twin on a CPU gets a C++ wrapper
        (``cpp_wrapper``): the compiled substep allocates its ~100 intermediate component buffers
        and calls its kernel from C++ instead of Python, measured 25 % faster for the single env.
        A batched twin does not: there it was 7 % faster at 256 and 1024 envs (2026-11-23), but
        compiling the wrapper is a second large C++ build, and with ``pyramid_contact`` the cold
        compile measured 139 s with it against 104 s without (64 envs, float32, the same load),
        the substep's speed the same (2,627 and 2,683 env steps/s). Inductor's default
        vectorisation (16 float32 lanes here) is kept: every tensor of the component-form step is
        (*B, n) with no trailing 3, and the scalar loops (``cpp.simdlen=1``) the tensor form needed
        measured 1.8x slower."""
        return {"cpp_wrapper": True} if self.engine.device.type == "cpu" and self.batch is None else {}

    # ------------------------------------------------------------------ read-out
    def states_numpy(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pos, quat, vel, angvel) as new float64 arrays (*B, R, ·); NaN for diverged copies."""
        flat = torch.cat(tuple(self.state), dim=-1).detach().to("cpu", torch.float64).numpy()
        out = (flat[..., 0:3], flat[..., 3:7], flat[..., 7:10], flat[..., 10:13])
        bad = self.diverged.cpu().numpy()
        if bad.any():
            out = tuple(np.where(bad[..., None, None], np.nan, x) for x in out)
        return out  # type: ignore[return-value]

    def rest_numpy(self) -> np.ndarray:
        """(*B, S) float64 rest lengths of every spring, m."""
        return self.rest.detach().to("cpu", torch.float64, copy=True).numpy()


def _split(state: RodState) -> tuple:
    """A stacked state -> the contiguous components of each field (the substep's form)."""
    return tuple(tuple(c.contiguous() for c in x.unbind(-1)) for x in state)


def _stack(comps: tuple) -> RodState:
    """The substep's components -> a stacked :class:`RodState` (*B, R, ·)."""
    return RodState(*(torch.stack(tuple(c), -1) for c in comps))
