#!/usr/bin/env python
"""Print the generated parts of docs/ARCHITECTURE.md: the layers (from the import-linter contracts
of pyproject.toml), the path of the data through the modules, and the effect library (from its
registry, :data:`identified.effects.EFFECTS`).

    python scripts/architecture.py           # rewrite the generated blocks of docs/ARCHITECTURE.md
    python scripts/architecture.py --check   # exit 1 if the document differs from what it would write

Each block sits between ``<!-- begin generated: NAME -->`` and ``<!-- end generated: NAME -->``;
tests/test_package.py checks the document is up to date.
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "ARCHITECTURE.md"

#: the path of the data, each stage by the module that does it (checked to exist)
DATA_PATH = (
    ("MJCF", "the system's structure and geometry, as MuJoCo compiles it", "identified.mjcf", "identified.topology"),
    ("recording", "rod states, commands and pushes of the plant", "tensegrity_gym.collect", None),
    ("lab recording", "markers, encoder rest lengths (CSV, C3D, Motive): read, checked, labelled",
     "identified.recording", None),
    ("rod states from markers", "rigid fits, smoothing splines, states at the engine step", "identified.fit.markers",
     None),
    ("dataset", "the `.npz` format, validating loader, atomic writer", "identified.dataset", None),
    ("samples", "accelerations from the recorded states", "identified.samples", None),
    ("regression", "the equations linear in the parameters, solved by streamed QR", "identified.fit.features",
     "identified.fit.regression"),
    ("marker fit", ("where the frames are too sparse for the regression: K, c, M and the contact law fitted to "
                    "the markers through the engine's windows (`fit R.csv --refine`)"), "identified.fit.marker_fit",
     "identified.fit.marker_model"),
    ("identified JSON", "the identified model as a person reads it", "identified.model", None),
    ("engine", "the spring-rod engine with the model's effects", "identified.twin", "identified.engine"),
    ("twin env", "the Gymnasium env on the identified engine", "tensegrity_gym.backends.identified_backend",
     "tensegrity_gym.envs.vector"),
    ("policy", "trained on the twin", "tensegrity_gym.training", None),
    ("gap", "the policy run on the plant and on the twin", "tensegrity_gym.gap", None),
)


def module_path(name: str) -> Path:
    """The source file of a module of this repository (a package's ``__init__.py``)."""
    base = ROOT.joinpath(*name.split("."))
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def summary(name: str) -> str:
    """The first sentence-line of a module's docstring, read without importing it."""
    path = module_path(name)
    if not path.is_file():
        raise SystemExit(f"architecture: module {name} does not exist ({path.relative_to(ROOT)})")
    doc = ast.get_docstring(ast.parse(path.read_text())) or ""
    first = doc.strip().split("\n\n")[0].replace("\n", " ")
    return re.sub(r"\s+", " ", first)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def layers_block() -> str:
    """Every layers contract of pyproject.toml as a table, top layer first."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    out = []
    for c in cfg["contracts"]:
        if c["type"] != "layers":
            continue
        out += [f"**{c['name']}**", "", "| layer | modules |", "| --- | --- |"]
        containers = c.get("containers", [""])
        rows = []
        for layer in c["layers"]:
            mods = []
            for p in (x.strip() for x in re.split(r"[|:]", layer)):
                optional = p.startswith("(")
                full = ".".join(x for x in (containers[0], p.strip("()")) if x)
                if module_path(full).is_file():
                    mods.append(f"`{full}`: {_cell(summary(full))}")
                elif not optional:
                    raise SystemExit(f"architecture: layer module {full} does not exist")
            if mods:  # an optional layer with no module yet is left out
                rows.append(mods)
        out += [f"| {len(rows) - k} | {'<br>'.join(mods)} |" for k, mods in enumerate(rows)]
        out.append("")
    others = [c for c in cfg["contracts"] if c["type"] != "layers"]
    out.append("Also checked:")
    out.append("")
    for c in others:
        out.append(f"* {c['name']} (`{c['type']}`)")
    return "\n".join(out).rstrip() + "\n"


def data_path_block() -> str:
    """The data path, one row per stage, each with the module(s) that do it."""
    out = ["| stage | what | where |", "| --- | --- | --- |"]
    for stage, what, first, second in DATA_PATH:
        mods = [m for m in (first, second) if m]
        for m in mods:
            summary(m)  # the module exists
        out.append(f"| {stage} | {what} | {', '.join(f'`{m}`' for m in mods)} |")
    return "\n".join(out) + "\n"


def effects_block() -> str:
    """The effect library from its registry: name, description, parameters, fit strategy, twin step."""
    sys.path.insert(0, str(ROOT))
    from identified.effects import EFFECTS, RESERVED

    out = ["| effect | what it adds | parameters | fit strategy | twin's fused step |",
           "| --- | --- | --- | --- | --- |"]
    for name, cls in EFFECTS.items():
        params = ", ".join(f"{b.name} ({b.per})" for b in cls.blocks)
        variants = "".join(f"; variant `{name}:{v}`" for v in cls.variants)
        fused = "yes" if cls.component_form else "no (tensor-form step)"
        out.append(f"| `{name}` | {_cell(cls.description)}{variants} | {params} | {cls.fit_strategy} | {fused} |")
    for name, why in RESERVED.items():
        out.append(f"| `{name}` | reserved, not available: {_cell(why)} | | | |")
    return "\n".join(out) + "\n"


BLOCKS = {"layers": layers_block, "data-path": data_path_block, "effects": effects_block}


def render(text: str) -> str:
    """``text`` with every generated block replaced by what the code says now."""
    for name, make in BLOCKS.items():
        pat = re.compile(rf"(<!-- begin generated: {name} -->\n).*?(<!-- end generated: {name} -->)", re.DOTALL)
        if not pat.search(text):
            raise SystemExit(f"architecture: {DOC.relative_to(ROOT)} has no generated block '{name}'")
        body = make()
        text = pat.sub(lambda m, body=body: m.group(1) + body + m.group(2), text)
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/ARCHITECTURE.md is not up to date")
    args = ap.parse_args(argv)
    old = DOC.read_text()
    new = render(old)
    if args.check:
        if new != old:
            print("docs/ARCHITECTURE.md is out of date: run python scripts/architecture.py", file=sys.stderr)
            return 1
        return 0
    if new != old:
        tmp = DOC.with_suffix(".md.tmp")
        tmp.write_text(new)
        tmp.replace(DOC)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
