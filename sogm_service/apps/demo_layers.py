"""How the demo's fleet names its layers, and how the demo reads them back as classes.

Shared layers (the default): every robot's ISM carries ``layer=<class>``, so the map holds one
layer per class (``obstacle``, ``floor``, ``person``, ...) and the demo reads those names.

Per-robot layers (``demo --per-robot-layers``): the ISMs carry no layer, so the server names
each after its key's remainder, ``<robot>/<sensor>/<class>`` (``robot1/laser/obstacle``): every
robot keeps its own layers, the provenance of what the map says.  The demo then reads each class
through the glob pattern ``*/*/<class>`` (:mod:`sogm_service.core.classes`): one plane per
class, its robots' layers fused by the Bayesian rule, so the pictures, the IoU and the report
are per class as with shared layers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sogm_service.core import classes


def class_of(layer: str) -> str:
    """The class a layer or a class pattern names: its last chunk
    (``robot1/laser/obstacle`` and ``*/*/obstacle`` -> ``obstacle``)."""
    return layer.rsplit("/", 1)[-1]


def label(layer: str) -> str:
    """How the pictures and the IoU name a plane: a layer by its name, a class pattern by its
    class (``*/*/obstacle`` -> ``obstacle``)."""
    return class_of(layer) if classes.is_pattern(layer) else layer


@dataclass(frozen=True)
class DemoLayers:
    """The demo's layer naming: shared (one layer per class) or per robot."""

    per_robot: bool = False

    @property
    def mode(self) -> str:
        """``summary.json``'s ``layer_mode``: ``shared`` or ``per_robot``."""
        return "per_robot" if self.per_robot else "shared"

    def entry(self, cls: str) -> str:
        """What the demo asks for a class: its layer, or the pattern of every robot's."""
        return f"*/*/{cls}" if self.per_robot else cls

    def entries(self, names: Sequence[str], skip: Sequence[str] = ()) -> list[str]:
        """The entries of the map's classes (``names``: its layers), those in ``skip`` left
        out, in the order the map lists their first layer."""
        if not self.per_robot:
            return [n for n in names if n not in skip]
        found = dict.fromkeys(class_of(n) for n in names if n.count("/") == 2)
        return [self.entry(c) for c in found if c not in skip]

    def summary(self, entries: Sequence[str], names: Sequence[str]) -> dict[str, Any]:
        """``summary.json``'s ``classes``: per class, the entry asked and its member layers."""
        resolved = classes.resolve(list(entries), list(names), allow_empty=True)
        return {class_of(c.name): {"entry": c.name, "members": list(c.members)}
                for c in resolved}


def has_layer(client: Any, entry: str) -> bool:
    """Whether the map holds ``entry``'s layer, or a layer its pattern matches."""
    found = classes.resolve([entry], list(client.info().layers), allow_empty=True)
    return bool(found[0].members)
