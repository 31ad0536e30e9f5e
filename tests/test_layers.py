"""The packages' layers import one way only (docs/CONTRACTS.md), checked on the source's import
statements (module level and inside functions alike)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# (files, forbidden import prefixes, allowed exceptions inside those files)
RULES: list[tuple[str, tuple[str, ...]]] = [
    ("gym_coffee", ("lgp_policy",)),
    (
        "lgp_policy/gp",
        (
            "gym_coffee",
            "lgp_policy.lfd",
            "lgp_policy.residual",
            "lgp_policy.baselines",
            "lgp_policy.app",
            "lgp_policy.rollout",
            "torch",
            "stable_baselines3",
            "gymnasium",
            "pybullet",
        ),
    ),
    (
        "lgp_policy/lfd",
        (
            "gym_coffee",
            "lgp_policy.residual",
            "lgp_policy.baselines",
            "lgp_policy.app",
            "torch",
            "stable_baselines3",
        ),
    ),
    ("lgp_policy/baselines", ("gym_coffee", "lgp_policy.residual", "lgp_policy.app")),
    ("lgp_policy/residual", ("gym_coffee", "lgp_policy.baselines", "lgp_policy.app")),
    ("lgp_policy/rollout.py", ("gym_coffee", "lgp_policy.app")),
    ("lgp_policy/_io.py", ("gym_coffee", "lgp_policy.gp", "lgp_policy.lfd", "lgp_policy.app")),
]
# The one place where the learning-from-demonstration layer meets the coffee task.
ADAPTERS = {"lgp_policy/lfd/adapters/coffee.py"}


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


def _files(where: str) -> list[Path]:
    path = ROOT / where
    return [path] if path.suffix == ".py" else sorted(path.rglob("*.py"))


@pytest.mark.parametrize(("where", "forbidden"), RULES, ids=[r[0] for r in RULES])
def test_layer_imports_point_one_way(where, forbidden):
    files = _files(where)
    assert files, f"no Python files under {where}"
    bad = []
    for path in files:
        rel = path.relative_to(ROOT).as_posix()
        if rel in ADAPTERS:
            continue
        for name in _imports(path):
            if any(name == f or name.startswith(f + ".") for f in forbidden):
                bad.append(f"{rel} imports {name}")
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_the_rule_catches_a_violation(tmp_path):
    """The checker itself sees a function-level import (so the test above can fail)."""
    src = tmp_path / "m.py"
    src.write_text(
        "def f():\n    from gym_coffee.env import OBS_SLICES\n    import lgp_policy.app\n"
    )
    assert _imports(src) == ["gym_coffee.env", "lgp_policy.app"]
