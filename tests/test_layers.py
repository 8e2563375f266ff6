"""The package's layers point one way: file primitives and errors at the bottom, then maths, then
learning and the pool protocol side by side (neither imports the other), then the commands. Checked on every module's imports,
those inside functions included."""

import ast
import os

import pytest

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "rl_pool")

LAYERS = {
    # errors, thread caps, versions, bounded reads and atomic writes: used by every layer
    "base": {"errors", "threads", "versions", "fsutil"},
    # pure maths and the data they work on: no processes, no pool files
    "maths": {"policy", "returns", "normalizer", "learner", "merge", "selection", "layout", "agent", "config"},
    # one member's learning: environments, rollouts, training and evaluation
    "learning": {"envs", "rollout", "trainer"},
    # the shared directory: reading, verifying, deciding and writing pool files
    "protocol": {"claim", "keys", "pool", "heartbeat", "barrier", "doctor"},
    # what a user runs: members, launcher, readers of pools, the command line
    "commands": {"member", "launch", "cli", "status", "progress", "plot", "replay", "pick", "compare", "tb",
                 "evaluate", "examples", "presets", "__main__", "__init__"},
}
MAY_IMPORT = {"base": {"base"}, "maths": {"base", "maths"}, "learning": {"base", "maths", "learning"},
              "protocol": {"base", "maths", "protocol"}, "commands": set(LAYERS)}


def _layer(module):
    return next(layer for layer, mods in LAYERS.items() if module in mods)


def _imports(path):
    tree = ast.parse(open(path).read())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module:
                out.add(node.module.split(".")[0])
            elif node.level == 1:
                out.update(a.name for a in node.names)
            elif node.module and node.module.split(".")[0] == "rl_pool":
                parts = node.module.split(".")
                out.update([parts[1]] if len(parts) > 1 else [a.name for a in node.names])
    return out


MODULES = sorted(f[:-3] for f in os.listdir(PACKAGE) if f.endswith(".py"))


def test_every_module_has_a_layer():
    assert [m for m in MODULES if not any(m in mods for mods in LAYERS.values())] == []


@pytest.mark.parametrize("module", MODULES)
def test_imports_point_down(module):
    here = _layer(module)
    wrong = {m: _layer(m) for m in _imports(os.path.join(PACKAGE, module + ".py"))
             if m in MODULES and _layer(m) not in MAY_IMPORT[here]}
    assert not wrong, f"{module} ({here}) imports {wrong}"
