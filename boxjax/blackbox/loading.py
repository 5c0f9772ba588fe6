"""The black-box models by method name, and their online adaptation."""

from __future__ import annotations

from boxjax.blackbox import baseline, pets
from boxjax.config import DEFAULT, GripperConfig

BLACK_BOXES = ("blackbox", "pets")  # methods with a learned model in the slot (no exploration, adapted)


def load_black_box(method: str, weights: str | None = None, gripper: GripperConfig = DEFAULT.gripper):
    """The model of a black-box method: "blackbox" (W, `baseline`) or "pets" (`pets`), the shipped
    weights unless `weights` names a checkpoint (refused by name if it is not that method's)."""
    if method == "blackbox":
        return baseline.default_model(gripper) if weights is None else baseline.load(weights, gripper=gripper)
    if method == "pets":
        return pets.default_model(gripper) if weights is None else pets.load(weights, gripper=gripper)
    raise ValueError(f"unknown black-box method {method!r}; choose one of {BLACK_BOXES}")


def adapter_for(model, epochs: int = 1):
    """The online adaptation of `model` (PETS's or W's; a DriftCorrected wrapper is looked through), or
    None when epochs < 1."""
    if epochs < 1:
        return None
    inner = getattr(model, "model", model)
    return (
        pets.make_adapter(epochs)
        if pets.is_pets(model) or pets.is_pets(inner)
        else baseline.make_adapter(epochs)
    )
