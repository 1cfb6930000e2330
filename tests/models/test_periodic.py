"""Periodic states (angles): declared by systems, plug-ins and `mpnode import --periodic`,
recorded in datasets (format version 3) and checkpoints, embedded as (sin θ, cos θ) by
MP-NODE's `--periodic embed`, and compared mod 2π under `--wrap-angles`.

References are independent of the code under test: numpy's own sin/cos and arctan2, files
written by h5py directly and edited by hand.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.hdf5 import read_dataset, read_header
from mpnode_cli.data.validate import check_dataset

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fitzhugh_nagumo.py"


# --- 1. Declaration ----------------------------------------------------------------------

def test_built_in_systems_declare_their_angles():
    from mpnode_cli.systems.registry import SYSTEMS

    assert SYSTEMS["kuramoto"].periodic_states == ("theta1", "theta2", "theta3")
    assert SYSTEMS["pendulum"].periodic_states == ("theta",)
    for name, cls in SYSTEMS.items():
        assert set(cls.periodic_states) <= set(cls.state_names), name
    assert SYSTEMS["lorenz"].periodic_states == ()


def test_a_plugin_declares_periodic_states_and_a_bad_name_is_refused(tmp_path):
    from mpnode_cli.systems.registry import load_system_file

    source = EXAMPLE.read_text()
    anchor = '    state_names: ClassVar[tuple[str, ...]] = ("v", "w")\n'
    assert anchor in source
    good = tmp_path / "good.py"
    good.write_text(source.replace(anchor, anchor + '    periodic_states = ("w",)\n'))
    assert load_system_file(good).periodic_states == ("w",)
    bad = tmp_path / "bad.py"
    bad.write_text(source.replace(anchor, anchor + '    periodic_states = ("phi",)\n'))
    line = one_line_error(invoke("generate", "--system-file", bad, "--out", tmp_path / "x.h5"))
    assert "declares periodic_states = ('phi',), not a tuple of distinct names among its " \
           "state_names" in line, line


def test_a_kuramoto_dataset_generated_now_declares_its_phases(tmp_path):
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    path = generate(GenerateConfig(system="kuramoto", nodes=6, trajectories=3, t_end=0.1,
                                   dt=0.05, out=tmp_path / "k.h5")).path
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 3
        assert json.loads(f.attrs["periodic_states"]) == ["theta1", "theta2", "theta3"]
    assert read_dataset(path).periodic_states == ("theta1", "theta2", "theta3")
    assert TrajectoryData.load(path).attrs["periodic_states"] == ("theta1", "theta2", "theta3")
    assert check_dataset(path).ok


# --- 2. Format: import, and files from before version 3 ----------------------------------

@pytest.fixture
def arrays(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "s.npy", rng.normal(size=(4, 5, 3, 2)))
    np.save(tmp_path / "a.npy", np.ones((3, 3), np.uint8))
    return tmp_path


def test_import_periodic_records_the_names(arrays):
    out = arrays / "d.h5"
    result = invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                    "--dt", 0.1, "--state-names", "q,p", "--periodic", "q", "--out", out)
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["periodic_states"]) == ["q"]
    assert read_dataset(out).periodic_states == ("q",)
    assert read_header(out)["attrs"]["periodic_states"] == ["q"]
    assert check_dataset(out).ok
    plain = arrays / "plain.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--out", plain).exit_code == 0
    assert read_dataset(plain).periodic_states == ()


def test_import_refuses_a_periodic_name_that_is_no_state(arrays):
    out = arrays / "d.h5"
    line = one_line_error(invoke("import", "--states", arrays / "s.npy", "--adjacency",
                                 arrays / "a.npy", "--dt", 0.1, "--periodic", "theta",
                                 "--out", out))
    assert "--periodic 'theta' is not a state name (states: x0, x1)" in line, line
    assert not out.exists()


def _as_version_2(path: Path) -> None:
    """Make a file written now into the version 2 file it would have been: no
    `periodic_states` attribute, format_version 2."""
    with h5py.File(path, "r+") as f:
        del f.attrs["periodic_states"]
        f.attrs["format_version"] = 2


def test_a_version_2_dataset_loads_with_no_periodic_states(arrays):
    out = arrays / "d.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--periodic", "x0", "--out", out).exit_code == 0
    _as_version_2(out)
    assert check_dataset(out).ok
    assert read_dataset(out).periodic_states == ()
    assert read_header(out)["attrs"]["periodic_states"] == []
    assert TrajectoryData.load(out).attrs["periodic_states"] == ()


def test_a_dataset_whose_periodic_states_are_not_state_names_is_refused(arrays):
    out = arrays / "d.h5"
    assert invoke("import", "--states", arrays / "s.npy", "--adjacency", arrays / "a.npy",
                  "--dt", 0.1, "--out", out).exit_code == 0
    with h5py.File(out, "r+") as f:
        f.attrs["periodic_states"] = json.dumps(["nope"])
    report = check_dataset(out)
    assert not report.ok
    assert any("periodic_states" in p for p in report.problems), report.problems


def test_wrapped_difference_reference_constants():
    """numpy's own: atan2(sin π, cos π) is π (to rounding), the reference below leans on."""
    assert abs(abs(math.atan2(math.sin(math.pi), math.cos(math.pi))) - math.pi) < 1e-15


# --- 3. Model: (sin θ, cos θ) in place of θ ---------------------------------------------

def _periodic_model(dims=(0,), members: int = 1, **options):
    import torch

    from mpnode_cli.models.registry import build_model

    torch.manual_seed(0)
    config = {"node_dim": 2, "control_dim": 0, "periodic": "embed", "periodic_dims": list(dims),
              **options}
    if members > 1:
        config["members"] = members
    return build_model("mpnode", config).double()


@pytest.mark.parametrize("options", [{}, {"update": "affine", "message_init": "learned"},
                                     {"aggregate": "sum"}])
def test_a_periodic_models_field_is_invariant_to_a_turn(options):
    import torch

    model = _periodic_model(**options)
    g = torch.Generator().manual_seed(1)
    z = torch.randn(3, 4, 2 + model.message_dim, generator=g, dtype=torch.float64) * 20
    adjacency = torch.ones(3, 4, 4, dtype=torch.float64)
    f = model.vector_field(adjacency)
    t = torch.zeros(3, dtype=torch.float64)
    turned = z.clone()
    turned[..., 0] += 2 * math.pi
    with torch.no_grad():
        a, b = f(t, z), f(t, turned)
        m0a = model.initial_messages(z[..., :2], None)
        m0b = model.initial_messages(turned[..., :2], None)
    # sin and cos of θ and θ + 2π differ by rounding: about u·|θ + 2π| each, u = 2⁻⁵³,
    # carried through weights of size ≈ 1 (Glorot) and a few layers: a margin of 10⁴.
    u = torch.finfo(torch.float64).eps / 2
    tol = 1e4 * u * float(turned[..., 0].abs().max() + 1)
    assert float((a - b).abs().max()) <= tol
    assert float((m0a - m0b).abs().max()) <= tol
    # ... while θ̇ and the messages do matter: the other component is no angle.
    other = z.clone()
    other[..., 1] += 2 * math.pi
    with torch.no_grad():
        assert float((f(t, other) - a).abs().max()) > 1e-6


def test_periodic_off_is_todays_model_and_embed_widens_the_input():
    from mpnode_cli.models.registry import build_model

    off = build_model("mpnode", {"node_dim": 2, "control_dim": 0})
    assert "periodic_dims" not in off.config and off.options.periodic == "off"
    on = _periodic_model()
    assert on.net[0].in_features == off.net[0].in_features + 1  # sin θ and cos θ for θ
    assert on.config["periodic_dims"] == [0]
    again = build_model("mpnode", on.config)
    assert again.periodic_dims == (0,) and again.config == on.config
    with pytest.raises(ValueError, match="declares none"):
        build_model("mpnode", {"node_dim": 2, "control_dim": 0, "periodic": "embed"})


def test_an_ensemble_of_periodic_models_rolls_out_like_its_members():
    import torch

    from mpnode_cli.models.ensemble import Ensemble

    torch.manual_seed(0)
    members = [_periodic_model() for _ in range(2)]
    for k, m in enumerate(members):
        torch.manual_seed(k)
        for p in m.parameters():
            p.data.normal_(0, 0.3)
    ensemble = Ensemble(members).double()
    x0 = torch.randn(2, 3, 2, dtype=torch.float64) * 5
    ts = torch.linspace(0, 0.3, 4, dtype=torch.float64)
    adjacency = torch.ones(2, 3, 3, dtype=torch.float64)
    with torch.no_grad():
        out = ensemble.rollout(x0, ts, adjacency)
        alone = torch.stack([m.rollout(x0, ts, adjacency).states for m in members])
    torch.testing.assert_close(out.states, alone.mean(0), rtol=1e-6, atol=1e-6)


# --- 2b/3. Checkpoints record the periodic states; a version 6 file reads with none -------

@pytest.fixture(scope="module")
def kuramoto_run(tmp_path_factory):
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import generate

    root = tmp_path_factory.mktemp("periodic")
    data = generate(GenerateConfig(system="kuramoto", nodes=6, trajectories=6, t_end=0.2,
                                   dt=0.05, out=root / "k.h5")).path
    # No --periodic: mpnode's recipe embeds the angles a dataset declares ("auto").
    result = invoke("train", data, "--epochs", 1, "--batch-size", 6, "--no-plots",
                    "--hidden", 8, "--run-dir", root / "run")
    assert result.exit_code == 0, result.output
    return {"data": data, "run": root / "run",
            "checkpoint": root / "run" / "checkpoints" / "best.pt"}


def test_a_periodic_run_records_its_angles_and_leaves_them_unscaled(kuramoto_run):
    from mpnode_cli.training.checkpoint import load_checkpoint

    ckpt = load_checkpoint(kuramoto_run["checkpoint"])
    assert ckpt.dataset["periodic_states"] == ["theta1", "theta2", "theta3"]
    assert ckpt.model_config["periodic"] == "embed"
    assert ckpt.model_config["periodic_dims"] == [0, 1, 2]
    assert ckpt.normalizer["x_mean"] == [0.0, 0.0, 0.0]
    assert ckpt.normalizer["x_std"] == [1.0, 1.0, 1.0]
    assert ckpt.build_model().periodic_dims == (0, 1, 2)
    result = invoke("evaluate", kuramoto_run["checkpoint"], kuramoto_run["data"], "--json")
    assert result.exit_code == 0, result.output


def test_the_recipes_periodic_choice_is_off_where_the_data_declare_no_angles(user_files):
    from mpnode_cli.models.options import MPNODEOptions
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.recipe import recipe_values

    ckpt = load_checkpoint(user_files["checkpoint"])  # mpnode's recipe, data without angles
    assert ckpt.model_config["periodic"] == "off"
    assert "periodic_dims" not in ckpt.model_config
    assert recipe_values("mpnode", {}, 101)["model_options"]["periodic"] == "auto"
    # The paper's recipe keeps the paper's model: the option's own default.
    assert "periodic" not in recipe_values("paper", {}, 101)["model_options"]
    assert MPNODEOptions().periodic == "off"


def test_periodic_embed_on_a_dataset_without_angles_is_one_line(user_files, tmp_path):
    line = one_line_error(invoke("train", user_files["data"], "--epochs", 1, "--no-plots",
                                 "--periodic", "embed", "--run-dir", tmp_path / "r"))
    assert "declares no periodic states" in line, line


def test_a_version_6_checkpoint_reads_with_no_periodic_states(user_files, tmp_path):
    import torch

    from mpnode_cli.training.checkpoint import FORMAT_VERSION, load_checkpoint

    assert FORMAT_VERSION == 8
    raw = torch.load(user_files["checkpoint"], weights_only=True)
    assert raw["format_version"] == 8 and raw["dataset"]["periodic_states"] == []
    # What version 6 wrote: the same, less the periodic states.
    raw["format_version"] = 6
    del raw["dataset"]["periodic_states"], raw["payload_sha256"]  # neither in version 6
    torch.save(raw, tmp_path / "v6.pt")
    ckpt = load_checkpoint(tmp_path / "v6.pt")
    assert ckpt.dataset["periodic_states"] == []
    assert ckpt.build_model().config == raw["model_config"]
    result = invoke("simulate", tmp_path / "v6.pt", "--x0", user_files["x0"], "--adjacency",
                    user_files["adjacency"], "--t-end", 0.2, "--dt", 0.1, "--out",
                    tmp_path / "p.h5")
    assert result.exit_code == 0, result.output
    assert read_dataset(tmp_path / "p.h5").periodic_states == ()


# --- 4. Errors mod 2π -------------------------------------------------------------------

def test_the_wrapped_difference_of_a_turn_is_zero_and_of_half_a_turn_is_pi():
    import torch

    from mpnode_cli.training.losses import Angles, difference, mse_loss

    theta = torch.linspace(-30, 30, 61, dtype=torch.float64)
    angles = Angles((0,))
    x = torch.stack([theta, theta], dim=-1)  # component 0 an angle, 1 not
    turned = x + 2 * math.pi
    d = difference(turned, x, angles)
    u = torch.finfo(torch.float64).eps / 2
    # θ + 2π − θ is 2π up to the rounding of θ + 2π (u·|θ + 2π|); wrapping leaves that.
    assert float(d[:, 0].abs().max()) <= 4 * u * float(turned.abs().max())
    torch.testing.assert_close(d[:, 1], torch.full_like(theta, 2 * math.pi))
    half = difference(x + math.pi, x, angles)[:, 0].abs()
    torch.testing.assert_close(half, torch.full_like(theta, math.pi), rtol=0,
                               atol=8 * u * float(turned.abs().max()))
    # In normalized units (std 0.5 rad per unit), the wrapped error is a turn's too.
    scaled = Angles((0,), torch.tensor([0.5, 3.0], dtype=torch.float64))
    dn = difference(x / 0.5 + 2 * math.pi / 0.5, x / 0.5, scaled)
    assert float(dn[:, 0].abs().max()) <= 1e-12
    # mse of [θ + π] against θ (t₀ excluded): π² on the angle, mean with the other's 0.
    pred = x[None, :, None, :].clone()
    target = pred.clone()
    pred[..., 0] += math.pi
    loss = mse_loss(pred, target, angles)
    assert abs(float(loss) - math.pi**2 / 2) <= 1e-9
    assert abs(float(mse_loss(pred, target)) - math.pi**2 / 2) <= 1e-9  # plain: the same
    pred[..., 0] += 2 * math.pi  # 3π: wrapped π again, plain 3π
    assert abs(float(mse_loss(pred, target, angles)) - math.pi**2 / 2) <= 1e-9
    assert abs(float(mse_loss(pred, target)) - 9 * math.pi**2 / 2) <= 1e-9


def test_wrapping_needs_both_the_declaration_and_the_opt_in():
    import torch

    from mpnode_cli.training.losses import run_angles

    facts = {"state_names": ["theta", "w"], "periodic_states": ["theta"]}
    std = torch.tensor([2.0, 1.0])
    assert run_angles(False, facts, std) is None
    assert run_angles(True, {"state_names": ["theta", "w"]}, std) is None
    angles = run_angles(True, facts, std)
    assert angles.dims == (0,) and angles.scale.tolist() == [2.0, 1.0]


def test_a_run_with_wrap_angles_reports_wrapped_errors(kuramoto_run, tmp_path):
    from mpnode_cli.training.checkpoint import load_checkpoint

    result = invoke("train", kuramoto_run["data"], "--epochs", 1, "--batch-size", 6,
                    "--no-plots", "--wrap-angles", "--hidden", 8, "--run-dir", tmp_path / "w")
    assert result.exit_code == 0, result.output
    ckpt = load_checkpoint(tmp_path / "w" / "checkpoints" / "best.pt")
    assert ckpt.train_config["wrap_angles"] is True
    assert invoke("evaluate", tmp_path / "w", kuramoto_run["data"], "--json").exit_code == 0
