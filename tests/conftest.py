"""Test-suite settings: the twin runs eagerly unless a test asks for ``compile=True``.

``torch.compile`` of the twin's substep takes seconds per new shape; the suite builds dozens of
twins, so it turns the ``compile="auto"`` default off (the compiled path has its own tests in
tests/test_twin_speed.py).
"""

import os

os.environ.setdefault("TENSEGRITY_TWIN_COMPILE", "0")
