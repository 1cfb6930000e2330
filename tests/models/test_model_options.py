"""Models' declared options and the registry: validation, defaults, rebuilding, no torch."""

from __future__ import annotations

import subprocess
import sys
from typing import get_args

import pytest

from mpnode_cli.models.options import Activation, MPNODEOptions
from mpnode_cli.models.registry import OPTIONS, build_model, model_class, resolve_options

SIZES = {"node_dim": 2, "control_dim": 1, "num_nodes": 3}


def test_each_model_declares_its_options_and_kind():
    for kind, options in OPTIONS.items():
        cls = model_class(kind)
        assert cls.kind == kind and cls.Options is options
        for name, field in options.model_fields.items():
            assert field.description, (kind, name)  # it is the CLI's help


def test_options_left_out_take_the_models_defaults():
    assert resolve_options("mpnode", {}).model_dump() == {
        "message_dim": 3, "hidden": 32, "layers": 2, "activation": "tanh", "graph": "sys",
        "messages": True, "aggregate": "mean", "update": "mlp", "message_init": "zero",
        "periodic": "off", "backend": "auto"}
    assert resolve_options("gnode", {"hidden": 8}).model_dump() == {
        "hidden": 8, "depth": 1, "graph": "sys", "aggregate": "sum"}


def test_an_unknown_option_or_a_bad_value_is_one_clear_line():
    with pytest.raises(ValueError, match=r"^model 'gnode' has no option 'message_dim' "
                                         r"\(its options: hidden, depth, graph, aggregate\)$"):
        resolve_options("gnode", {"hidden": 8, "message_dim": 2})
    with pytest.raises(ValueError, match=r"model 'mpnode' option graph: Input should be 'sys' "
                                         r"or 'full' \(got 'ring'\)"):
        resolve_options("mpnode", {"graph": "ring"})
    with pytest.raises(ValueError, match=r"model 'l2s' option steps: .* greater than or equal"):
        resolve_options("l2s", {"steps": 0})
    with pytest.raises(ValueError, match=r"unknown model 'nope' \(choose from: mpnode, l2s"):
        resolve_options("nope", {})
    with pytest.raises(ValueError, match="model 'node' has no option 'depth'"):
        build_model("node", {"node_dim": 2, "num_nodes": 3, "depth": 2})


@pytest.mark.parametrize("kind", list(OPTIONS))
def test_config_rebuilds_the_same_model(kind):
    import torch

    options = resolve_options(kind, {"hidden": 8})
    torch.manual_seed(0)
    model = model_class(kind)(SIZES["node_dim"], SIZES["control_dim"], SIZES["num_nodes"],
                              options)
    config = model.config
    assert config == {k: v for k, v in SIZES.items()
                      if k != "num_nodes" or not model.transferable} | options.model_dump()
    torch.manual_seed(0)
    again = build_model(kind, config)
    assert again.config == config and again.options == options
    for (name, a), (_, b) in zip(model.state_dict().items(), again.state_dict().items(),
                                 strict=True):
        assert torch.equal(a, b), name


def test_a_monolithic_model_needs_its_node_count():
    with pytest.raises(ValueError, match="built for one node count"):
        build_model("node", {"node_dim": 2})


def test_options_are_frozen_with_the_model():
    with pytest.raises(ValueError, match="frozen"):
        MPNODEOptions().hidden = 8


def test_activation_choices_are_the_ones_the_models_build():
    from mpnode_cli.models.base import ACTIVATIONS

    assert tuple(ACTIVATIONS) == get_args(Activation)


def test_options_and_registry_import_without_torch():
    code = ("import sys\n"
            "from mpnode_cli.models.registry import OPTIONS, resolve_options\n"
            "resolve_options('l2s', {'history': 2})\n"
            "print('TORCH', 'torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert "TORCH False" in out
