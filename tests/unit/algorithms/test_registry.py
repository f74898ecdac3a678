"""The generic Registry: lookup, errors that list names, duplicates, entry-point plugins."""

import types

import pytest

from infinirl import registry as registry_module
from infinirl.algorithms import (
    ADVANTAGES,
    AGGREGATIONS,
    KL_ESTIMATORS,
    POLICY_LOSSES,
    Registry,
    UnknownNameError,
)


def test_register_get_and_names_sorted():
    reg = Registry("widget")

    @reg.register("zeta")
    def zeta():
        return "z"

    reg.add("alpha", 1)
    assert reg.get("zeta") is zeta and zeta() == "z"  # the decorator returns the function itself
    assert reg.names() == ["alpha", "zeta"]
    assert "alpha" in reg and "beta" not in reg and len(reg) == 2 and list(reg) == ["alpha", "zeta"]


def test_unknown_name_error_lists_sorted_names_and_suggests():
    with pytest.raises(UnknownNameError) as caught:
        ADVANTAGES.get("grpoo")
    message = str(caught.value)
    assert message.startswith(
        "unknown advantage estimator 'grpoo'; registered: dr_grpo, embodied_gae, embodied_grpo, "
        "gae, grpo, reinforce_pp, reinforce_pp_baseline, rloo"
    )
    assert message.endswith("did you mean 'grpo'?")
    assert isinstance(caught.value, KeyError) and isinstance(caught.value, ValueError)


def test_unknown_name_in_empty_registry():
    with pytest.raises(ValueError, match=r"unknown robot 'ur5'; registered: \(none\)$"):
        Registry("robot").get("ur5")


def test_duplicate_registration_is_an_error_but_re_adding_same_object_is_not():
    reg = Registry("widget")
    obj = object()
    reg.add("a", obj)
    reg.add("a", obj)  # idempotent: re-importing a module must not fail
    with pytest.raises(ValueError, match="widget 'a' is already registered"):
        reg.add("a", object())
    with pytest.raises(ValueError, match="non-empty"):
        reg.add("", obj)


def test_entry_point_plugins_are_loaded_lazily(monkeypatch):
    calls = []

    class FakeEntryPoint:
        def __init__(self, name, loaded):
            self.name, self._loaded = name, loaded

        def load(self):
            calls.append(self.name)
            return self._loaded

    plugin_module = types.ModuleType("plugin_mod")
    reg = Registry("env", entry_point_group="infinirl.envs")

    def fake_entry_points(group):
        assert group == "infinirl.envs"
        reg.add("registered_by_import", "via-decorator")  # what importing a plugin module does
        return [FakeEntryPoint("direct", "env-object"), FakeEntryPoint("mod", plugin_module)]

    monkeypatch.setattr(registry_module.metadata, "entry_points", fake_entry_points)
    assert calls == []  # nothing loaded at construction
    assert reg.get("direct") == "env-object"
    assert reg.names() == ["direct", "registered_by_import"]  # a module entry is not an object
    reg.get("direct")
    assert calls == ["direct", "mod"]  # loaded once


def test_builtin_registries_hold_the_documented_names():
    assert ADVANTAGES.names() == sorted([
        "gae", "grpo", "dr_grpo", "rloo", "reinforce_pp", "reinforce_pp_baseline",
        "embodied_gae", "embodied_grpo",
    ])
    assert POLICY_LOSSES.names() == ["policy_gradient", "ppo_clip"]
    assert KL_ESTIMATORS.names() == ["k1", "k2", "k3"]
    assert AGGREGATIONS.names() == [
        "seq-mean-token-mean", "seq-mean-token-sum", "seq-mean-token-sum-norm", "token-mean",
    ]


def test_algorithms_package_imports_only_torch_and_stdlib():
    import ast
    import pathlib
    import sys

    import infinirl.algorithms

    package = pathlib.Path(infinirl.algorithms.__file__).parent
    allowed = {"torch", "infinirl", "__future__"} | set(sys.stdlib_module_names)
    for path in package.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                roots = [alias.name.split(".")[0] for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                roots = [node.module.split(".")[0]]
            else:
                continue
            for root in roots:
                assert root in allowed, f"{path.name} imports {root}"
            if isinstance(node, ast.ImportFrom) and roots == ["infinirl"]:
                # Only the algorithms package itself and the torch-free generic registry.
                assert node.module.startswith("infinirl.algorithms") or node.module == "infinirl.registry", (
                    f"{path.name}: {node.module}"
                )
