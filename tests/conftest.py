"""Test-suite settings: the twin runs eagerly unless a test asks for ``compile=True``.

``torch.compile`` of the twin's substep takes seconds per new shape; the suite builds dozens of
twins, so it turns the ``compile="auto"`` default off (the compiled path has its own tests in
tests/test_twin_speed.py), and keeps the compiled substep's cache on disk off: a test that wants
it names its own folder (tests/test_substep_cache.py).

torch runs on one intra-op thread (``OMP_NUM_THREADS=1``, inherited by the commands the tests
start): the suite's tensors are small, a second thread gains nothing on them, and where another
process is busy on the other core its spinning made single tests 2-16x slower (measured: a cable
friction rollout 0.7 s on one thread, 11.8 s on two beside a busy core). Tests of the thread
handling set their own counts.
"""

import os

os.environ.setdefault("TENSEGRITY_TWIN_COMPILE", "0")
os.environ.setdefault("TENSEGRITY_TWIN_CACHE", "0")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # after OMP_NUM_THREADS: torch reads it when it starts its thread pool)

torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
