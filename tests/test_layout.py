"""The package's structure: imports run one way, nothing happens at import, modules stay readable."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "gainfpn_cli"
#: What each part must never import (docs/layout.md): the math knows nothing of configs, files,
#: the pipeline, the simulator or the tools; files know nothing of the job; nothing below the
#: command line knows click or tqdm.
FORBIDDEN = {
    "geometry": {"config", "files", "outdir", "pipeline", "outputs", "burst", "sim", "tools", "cli", "motion", "solve"},
    "motion": {"config", "files", "outdir", "pipeline", "outputs", "burst", "sim", "tools", "cli", "solve"},
    "solve": {"config", "files", "outdir", "pipeline", "outputs", "burst", "sim", "tools", "cli", "motion"},
    "metrics": {"config", "files", "outdir", "pipeline", "outputs", "burst", "sim", "tools", "cli", "motion", "solve",
                "geometry"},
    "files": {"config", "outdir", "pipeline", "outputs", "burst", "sim", "tools", "cli", "motion", "solve",
              "geometry", "metrics", "preview", "summary", "report"},
    "pipeline": {"sim", "tools", "cli"},
    "outputs": {"sim", "tools", "cli"},
}
THIRD_PARTY_UI = {"click", "tqdm"}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).with_suffix("")
        yield ".".join(rel.parts), path


def _imports(name: str, path: Path) -> set[str]:
    """Top-level parts of gainfpn_cli imported by a module (at any depth, lazy imports included),
    and the third-party packages it imports."""
    package = name.split(".")[:-1] if not path.name == "__init__.py" else name.split(".")
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
                target = [*base, *(node.module.split(".") if node.module else [])]
                if not target:  # from . import x (the package itself)
                    target = [alias.name for alias in node.names][:1]
                found.add(target[0] if target else "")
            elif node.module and node.module.split(".")[0] == "gainfpn_cli":
                found.add(node.module.split(".")[1] if "." in node.module else "")
            elif node.module:
                found.add("ext:" + node.module.split(".")[0])
        elif isinstance(node, ast.Import):
            for alias in node.names:
                found.add("ext:" + alias.name.split(".")[0])
    return found


@pytest.mark.parametrize("name, path", list(_modules()), ids=[n for n, _ in _modules()])
def test_imports_run_one_way(name, path):
    part = name.split(".")[0]
    imported = _imports(name, path)
    assert not (imported & FORBIDDEN.get(part, set())), f"{name} imports {imported & FORBIDDEN[part]}"
    if part != "cli" and part != "tools":
        assert not {f"ext:{m}" for m in THIRD_PARTY_UI} & imported, f"{name} imports a user-interface library"


def test_no_module_is_over_450_lines():
    long = {name: n for name, path in _modules() if (n := len(path.read_text().splitlines())) > 450}
    assert not long, long


def test_importing_the_package_changes_nothing_and_loads_nothing_heavy():
    code = ("import os, sys; before = os.umask(0o022); os.umask(before); import gainfpn_cli.cli, gainfpn_cli.pipeline; "
            "after = os.umask(0o022); os.umask(after); "
            "print(before == after, 'cv2' in sys.modules, 'rawpy' in sys.modules, 'OpenImageIO' in sys.modules)")
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    assert out.split() == ["True", "False", "False", "False"]  # --help stays fast


def test_the_model_names_are_those_of_the_models():
    from gainfpn_cli import motion, solve
    from gainfpn_cli.config import Config
    from gainfpn_cli.motion.fields import FIELD_CELLS
    from gainfpn_cli.motion.fit import MODEL_PARAMS
    from gainfpn_cli.solve.fpnmodel import select_model

    assert motion.MODELS == (*MODEL_PARAMS, *FIELD_CELLS) and motion.ALL_MODELS == (*motion.MODELS, "layers")
    import numpy as np

    k, conf = np.ones((8, 8), np.float32), np.full((8, 8), 0.5, np.float32)
    assert set(select_model(k, conf).scores) == set(solve.FPN_MODELS)
    assert Config().motion.model == "auto" and Config().solver.fpn_model == "auto"


def test_the_command_line_loads_without_numpy():
    code = "import sys, gainfpn_cli.cli; print('numpy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"  # gainfpn --help: click, yaml and the package's light modules only
