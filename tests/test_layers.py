"""The package's layers point one way, and its folders show them: base modules (errors, thread
caps, versions, bounded file access) and the settings at the top of ``rl_pool/``, then
``maths/``, then ``learning/`` and ``protocol/`` side by side (neither imports the other), then
``commands/``. Checked on every module's imports, those inside functions included."""

import ast
import os

import pytest

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "rl_pool")

#: The top-level modules' layers; every other module's layer is its folder.
TOP = {"errors": "base", "threads": "base", "versions": "base", "fsutil": "base", "config": "settings",
       "__init__": "commands", "__main__": "commands"}
LAYERS = ("base", "maths", "settings", "learning", "protocol", "commands")
MAY_IMPORT = {"base": {"base"}, "maths": {"base", "maths"}, "settings": {"base", "maths", "settings"},
              "learning": {"base", "maths", "settings", "learning"},
              "protocol": {"base", "maths", "settings", "protocol"}, "commands": set(LAYERS)}


def _modules():
    out = {}
    for dirpath, _, files in os.walk(PACKAGE):
        rel = os.path.relpath(dirpath, PACKAGE)
        for f in files:
            if f.endswith(".py"):
                name = f[:-3] if rel == "." else f"{rel.replace(os.sep, '.')}.{f[:-3]}"
                out[name] = os.path.join(dirpath, f)
    return out


MODULES = _modules()


def _layer(module: str) -> str:
    head = module.split(".")[0]
    return TOP.get(head, head)


def _imports(path: str, module: str) -> set[str]:
    """The rl_pool modules ``path`` imports, as names relative to the package (``maths.agent``)."""
    package = module.rsplit(".", 1)[0] if "." in module else ""
    out = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1] if package else []
                parts = [p for p in base if p] + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == "rl_pool":
                parts = node.module.split(".")[1:]
            else:
                continue
            target = ".".join(parts)
            names = [f"{target}.{a.name}" if target else a.name for a in node.names]
            modules = [n for n in names if n in MODULES]
            if modules:
                out.update(modules)
            else:
                out.add(target)
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".", 1)[1] for a in node.names if a.name.startswith("rl_pool."))
    return {m for m in out if m in MODULES or m in LAYERS}


def test_every_module_has_a_known_layer():
    assert sorted(m for m in MODULES if _layer(m) not in LAYERS) == []


def test_the_folders_are_the_layers():
    folders = {d for d in os.listdir(PACKAGE) if os.path.isdir(os.path.join(PACKAGE, d)) and d != "__pycache__"}
    assert folders == {"maths", "learning", "protocol", "commands"}


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_point_down(module):
    here = _layer(module)
    wrong = {m: _layer(m) for m in _imports(MODULES[module], module) if _layer(m) not in MAY_IMPORT[here]}
    assert not wrong, f"{module} ({here}) imports {wrong}"


def test_the_import_check_sees_imports_inside_functions():
    # a guard against a check that passes because it reads nothing
    assert "protocol.doctor" in _imports(MODULES["protocol.pool"], "protocol.pool")
    assert "maths.agent" in _imports(MODULES["learning.trainer"], "learning.trainer")


def test_no_module_is_over_about_500_lines():
    long = {m: n for m, p in MODULES.items() if (n := sum(1 for _ in open(p))) > 520}
    assert not long, long
