"""Small helpers that hide differences between the Blender versions the add-on supports (4.2 to 5.0).

Blender 4.4 made actions layered ("slotted actions") and Blender 5.0 removed the 4.x shortcut
``Action.fcurves``; these helpers read and write F-curves and assign actions the same way on both.
"""

from __future__ import annotations


def action_fcurves(action) -> list:
    """Every F-curve of ``action``, on any Blender version."""
    layers = getattr(action, "layers", None)
    if layers:
        curves = []
        for layer in layers:
            for strip in layer.strips:
                for bag in getattr(strip, "channelbags", ()):
                    curves.extend(bag.fcurves)
        return curves
    return list(getattr(action, "fcurves", ()))


def assign_action(id_data, action) -> None:
    """Make ``action`` the active action of ``id_data`` (and give it a slot on Blender 4.4+)."""
    anim = id_data.animation_data or id_data.animation_data_create()
    anim.action = action
    if action is not None and hasattr(anim, "action_slot") and anim.action_slot is None:
        slots = getattr(action, "slots", ())
        if len(slots):
            anim.action_slot = slots[0]


def new_fcurve(action, id_data, data_path: str, index: int, group: str):
    """Create an F-curve on ``action`` (already assigned to ``id_data``) for ``data_path[index]``."""
    if hasattr(action, "fcurve_ensure_for_datablock"):  # Blender 4.4+; group_name since 5.0
        try:
            return action.fcurve_ensure_for_datablock(id_data, data_path, index=index, group_name=group)
        except TypeError:
            return action.fcurve_ensure_for_datablock(id_data, data_path, index=index)
    return action.fcurves.new(data_path, index=index, action_group=group)
