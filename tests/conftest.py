"""Test-suite settings: the twin runs eagerly unless a test asks for ``compile=True``.

``torch.compile`` of the twin's substep takes seconds per new shape; the suite builds dozens of
twins, so it turns the ``compile="auto"`` default off (the compiled path has its own tests in
tests/test_twin_speed.py), and keeps the compiled substep's cache on disk off: a test that wants
it names its own folder (tests/test_substep_cache.py).
"""

import os

os.environ.setdefault("TENSEGRITY_TWIN_COMPILE", "0")
os.environ.setdefault("TENSEGRITY_TWIN_CACHE", "0")
