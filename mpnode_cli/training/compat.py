"""Whether a trained model can run on a dataset: the one check that `evaluate`, `zeroshot`,
`finetune` and the experiments' steps make before they roll a checkpoint out on data.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mpnode_cli.models.registry import OPTIONS, model_class

if TYPE_CHECKING:
    from mpnode_cli.data.dataset import TrajectoryData


def check_compatible(model_kind: str, model_config: dict[str, Any], trained_nodes: int,
                     data: TrajectoryData, verb: str, trained_system: str | None = None, *,
                     allow_other_system: bool = False) -> None:
    """Raise a one-line `ValueError` when a trained model cannot run on `data`.

    A model learned one system's node dynamics in that system's normalization; on another
    system's data (of the same state size) it runs, but its numbers mean nothing, so that
    is refused unless asked for.

    Args:
        model_kind, model_config: the checkpoint's model.
        trained_nodes: N of the dataset the model was trained on.
        data: the dataset to run on.
        verb: what the user asked for ("finetune", "zeroshot", ...), for the message.
        trained_system: the `system` of the training dataset (None: not checked).
        allow_other_system: accept data of another system.
    """
    name = data.path.name
    for field, have in (("node_dim", data.node_dim), ("control_dim", data.control_dim)):
        want = int(model_config.get(field, 0))
        if have != want:
            what = "state" if field == "node_dim" else "control"
            raise ValueError(
                f"{name} has {field} {have} but the checkpoint expects {want}: {verb} needs "
                f"the same per-node {what} size")
    if trained_system is not None and data.system != trained_system and not allow_other_system:
        raise ValueError(
            f"{name} holds system '{data.system}' but the checkpoint was trained on "
            f"'{trained_system}': {verb} on another system needs --allow-other-system")
    transferable = model_kind not in OPTIONS or model_class(model_kind).transferable
    if not transferable and data.num_nodes != trained_nodes:
        raise ValueError(
            f"{name} has {data.num_nodes} nodes but model '{model_kind}' was trained on "
            f"{trained_nodes} and only runs on graphs of that size")
