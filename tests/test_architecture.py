"""The import rules of docs/architecture.md: every import in src/humimic, lazy ones included."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "humimic"

CORE = {"core"}
INPUTS = CORE | {"formats", "datasets", "robots"}
PARTS = {"retarget", "tracking", "real2sim"}
ALLOWED: dict[str, set[str]] = {
    "core": CORE,
    "formats": CORE,
    "datasets": CORE | {"formats"},
    "robots": CORE | {"formats"},
    "sim": INPUTS,
    "configs": INPUTS | {"sim"},
    "retarget": INPUTS | {"sim", "configs"},
    "tracking": INPUTS | {"sim", "configs"},
    "real2sim": INPUTS | {"sim", "configs"},
    "viewer": INPUTS | {"configs"},
    "pipeline": INPUTS | {"sim", "configs"} | PARTS,
    "cli": INPUTS | {"sim", "configs", "viewer", "pipeline"} | PARTS,
}
"""Layer -> the layers it may import (its own always). ``core`` is the top-level modules
(errors, io, transforms, motion, motion_checks, npyio, lazy)."""


def layer(module: str) -> str:
    """The layer of a ``humimic...`` module name."""
    parts = module.split(".")
    if len(parts) < 2 or (SRC / f"{parts[1]}.py").is_file():
        return "core"
    return parts[1]


def _module_of(path: Path, root: Path | None = None) -> str:
    """The dotted module name of a file under ``root`` (default: :data:`SRC`)."""
    rel = path.relative_to((root or SRC).parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imports(path: Path) -> list[tuple[int, str]]:
    """Every humimic module a file imports (line, module), at any depth of the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _module_of(path) if path.name == "__init__.py" else _module_of(path).rsplit(".", 1)[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names if a.name.startswith("humimic")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            if name == "humimic":  # from humimic import transforms
                out += [(node.lineno, f"humimic.{a.name}") for a in node.names]
            elif name.startswith("humimic."):
                out.append((node.lineno, name))
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and MODULE_PATH.fullmatch(node.value)
            and _is_module(node.value)
        ):
            # A module named in a string: importlib.import_module("humimic.x"), a lazy
            # attribute table's target, __import__: an import all the same.
            out.append((node.lineno, node.value))
    return out


MODULE_PATH = re.compile(r"humimic(\.[A-Za-z_][A-Za-z_0-9]*)+")


def _is_module(name: str) -> bool:
    """Whether a dotted ``humimic...`` name is a module or package under :data:`SRC`."""
    rel = Path(*name.split(".")[1:])
    return (SRC / rel).with_suffix(".py").is_file() or (SRC / rel / "__init__.py").is_file()


def violations(root: Path = SRC) -> list[str]:
    """Each import that breaks :data:`ALLOWED`, as ``file:line: a -> b``."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        mine = layer(_module_of(path))
        for line, module in imports(path):
            theirs = layer(module)
            if theirs != mine and theirs not in ALLOWED[mine]:
                bad.append(f"{path.relative_to(root.parent)}:{line}: {mine} -> {theirs} ({module})")
    return bad


def test_every_layer_is_known() -> None:
    found = {layer(_module_of(p)) for p in SRC.rglob("*.py")}
    assert found <= set(ALLOWED), f"layers without rules: {found - set(ALLOWED)}"


def test_import_rules_hold() -> None:
    bad = violations()
    assert not bad, "forbidden imports (see docs/architecture.md):\n" + "\n".join(bad)


def test_the_check_sees_lazy_and_relative_imports(tmp_path: Path) -> None:
    """A forbidden import inside a function, a relative one, ``from humimic import x`` and a
    module named in a string (``importlib.import_module``, a lazy table) are all found (the
    rule must not pass because the scanner is blind); a string that is not a module path is
    not."""
    pkg = tmp_path / "humimic"
    (pkg / "retarget").mkdir(parents=True)
    (pkg / "tracking").mkdir()
    (pkg / "errors.py").write_text("")
    (pkg / "retarget" / "a.py").write_text("def f():\n    from humimic.tracking import env\n")
    (pkg / "retarget" / "b.py").write_text("from ..tracking import env\n")
    (pkg / "sim").mkdir()
    (pkg / "sim" / "c.py").write_text("from humimic import tracking\nfrom humimic import errors\n")
    (pkg / "tracking" / "env.py").write_text("")
    (pkg / "retarget" / "d.py").write_text(
        "import importlib\n\ndef g():\n    return importlib.import_module('humimic.tracking.env')\n"
        "WHERE = {'Env': 'humimic.tracking.env', 'note': 'humimic.tracking is elsewhere'}\n"
    )
    global SRC
    saved, SRC = SRC, pkg
    try:
        bad = violations(pkg)
    finally:
        SRC = saved
    assert [b.split(": ", 1)[1] for b in bad] == [
        "retarget -> tracking (humimic.tracking)",
        "retarget -> tracking (humimic.tracking)",
        "retarget -> tracking (humimic.tracking.env)",
        "retarget -> tracking (humimic.tracking.env)",
        "sim -> tracking (humimic.tracking)",
    ], bad


@pytest.mark.parametrize("part", sorted(PARTS))
def test_the_parts_never_import_each_other(part: str) -> None:
    assert not (ALLOWED[part] & (PARTS - {part}))


STEPPERS = frozenset({"mj_step", "mj_step1", "mj_step2"})
"""MuJoCo's stepping functions: only ``sim/`` calls them (:mod:`humimic.sim.rollout`)."""


def physics_steps(root: Path = SRC) -> list[str]:
    """Each use of :data:`STEPPERS` outside ``sim/``, as ``file:line: name``: an attribute
    (``mujoco.mj_step``), a bare name, ``from mujoco import mj_step`` and a ``getattr`` by
    string. Docstrings and comments may mention them."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        if layer(_module_of(path, root)) == "sim":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            found = None
            if isinstance(node, ast.Attribute) and node.attr in STEPPERS:
                found = node.attr
            elif isinstance(node, ast.Name) and node.id in STEPPERS:
                found = node.id
            elif isinstance(node, ast.ImportFrom):
                found = next((a.name for a in node.names if a.name in STEPPERS), None)
            elif (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "getattr"
                and any(isinstance(a, ast.Constant) and a.value in STEPPERS for a in node.args)
            ):
                found = "getattr"
            if found:
                bad.append(f"{path.relative_to(root.parent)}:{getattr(node, 'lineno', 0)}: {found}")
    return bad


def test_only_sim_steps_physics() -> None:
    bad = physics_steps()
    assert not bad, "mj_step outside sim/ (step through humimic.sim.rollout):\n" + "\n".join(bad)


def test_the_step_check_sees_every_form(tmp_path: Path) -> None:
    """Each way of reaching ``mj_step`` outside ``sim/`` is found; ``sim/`` itself, a
    docstring and other MuJoCo calls are not."""
    pkg = tmp_path / "humimic"
    (pkg / "retarget").mkdir(parents=True)
    (pkg / "sim").mkdir()
    (pkg / "sim" / "ok.py").write_text("import mujoco\n\ndef f(m, d):\n    mujoco.mj_step(m, d)\n")
    (pkg / "retarget" / "a.py").write_text(
        '"""Steps with mj_step."""\nimport mujoco\n\ndef f(m, d):\n'
        "    mujoco.mj_forward(m, d)\n    mujoco.mj_step(m, d)\n"
    )
    (pkg / "retarget" / "b.py").write_text("from mujoco import mj_step2\n")
    (pkg / "retarget" / "c.py").write_text(
        "import mujoco\n\ndef g(m, d):\n    getattr(mujoco, 'mj_step1')(m, d)\n"
    )
    found = [b.split("humimic/", 1)[1] for b in physics_steps(pkg)]
    assert found == [
        "retarget/a.py:6: mj_step",
        "retarget/b.py:1: mj_step2",
        "retarget/c.py:4: getattr",
    ]


BOUNDARIES = {"rsl_rl": "humimic.tracking.rsl"}
"""Third-party packages that one module wraps: only it imports them."""


def boundary_breaches(root: Path = SRC) -> list[str]:
    """Each import of a :data:`BOUNDARIES` package outside its module, ``file:line: pkg``
    (lazy imports and ``importlib`` strings included)."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        mine = _module_of(path, root)
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                # A module path in a string (importlib, a class path such as "pkg.mod:Cls").
                names = [node.value] if re.fullmatch(r"[\w.:]+", node.value) else []
            for name in names:
                pkg = name.split(".")[0].split(":")[0]
                if pkg in BOUNDARIES and BOUNDARIES[pkg] != mine:
                    bad.append(
                        f"{path.relative_to(root.parent)}:{getattr(node, 'lineno', 0)}: {pkg}"
                    )
    return bad


def test_third_party_boundaries_hold() -> None:
    bad = boundary_breaches()
    assert not bad, "import through the boundary module instead:\n" + "\n".join(bad)


def test_the_boundary_check_sees_every_form(tmp_path: Path) -> None:
    pkg = tmp_path / "humimic"
    (pkg / "tracking").mkdir(parents=True)
    (pkg / "tracking" / "rsl.py").write_text("from rsl_rl.env import VecEnv\n")
    (pkg / "tracking" / "env.py").write_text(
        '"""Uses rsl_rl\'s runner."""\nimport importlib\n\ndef f():\n'
        "    import rsl_rl.runners\n    return importlib.import_module('rsl_rl.env')\n"
    )
    (pkg / "tracking" / "rma.py").write_text("from rsl_rl.modules import MLP\n")
    found = [b.split("humimic/", 1)[1] for b in boundary_breaches(pkg)]
    assert found == [
        "tracking/env.py:5: rsl_rl",
        "tracking/env.py:6: rsl_rl",
        "tracking/rma.py:1: rsl_rl",
    ]


MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80
"""Issue 58's bounds: a module a reader can hold, a function that fits a screen (its
docstring counted)."""


def oversized(root: Path = SRC) -> list[str]:
    """Each module over :data:`MAX_MODULE_LINES` lines and each function (or method) over
    :data:`MAX_FUNCTION_LINES`, as ``file: name (lines)``."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        rel = path.relative_to(root.parent)
        if (n := len(text.splitlines())) > MAX_MODULE_LINES:
            bad.append(f"{rel}: module ({n})")
        for node in ast.walk(ast.parse(text, filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    bad.append(f"{rel}: {node.name} ({n})")
    return bad


def test_modules_and_functions_stay_short() -> None:
    bad = oversized()
    assert not bad, "split these (docs/architecture.md):\n" + "\n".join(bad)


def test_the_size_check_counts_lines(tmp_path: Path) -> None:
    pkg = tmp_path / "humimic"
    pkg.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (pkg / "long.py").write_text(f"def f():\n{body}\n\n\ndef g():\n    return 1\n")
    (pkg / "big.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    (pkg / "ok.py").write_text("x = 1\n" * MAX_MODULE_LINES)
    found = [b.split("humimic/", 1)[1] for b in oversized(pkg)]
    assert found == [
        f"big.py: module ({MAX_MODULE_LINES + 1})",
        f"long.py: f ({MAX_FUNCTION_LINES + 1})",
    ]
