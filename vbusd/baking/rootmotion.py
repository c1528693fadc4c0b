"""Root motion extraction: a clip baked in place, with its root's motion kept as a track (spec "Root motion").

The track's data and math (:class:`vbusd.format.rootmotion.RootMotion`, ``at``, ``displacement``)
are the format's; this module takes the motion out of a sampled clip while baking.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from vbusd.format.rootmotion import matrices, track_entries

__all__ = ["in_place_clip"]


def in_place_clip(clip, root: int, bind_root: np.ndarray, up_axis: str, yaw: bool):
    """The clip with the root motion taken out of every bone: ``M' = D^-1 M`` at every time."""
    first = np.asarray(clip.sample(np.array([clip.start_time]))[0, root], dtype=np.float64) @ bind_root
    original = clip.sample

    def sample(times):
        poses = np.asarray(original(times), dtype=np.float64)
        entries = track_entries(poses[:, root] @ bind_root, first, up_axis, yaw)
        inverse = np.linalg.inv(matrices(entries, up_axis))
        return inverse[:, None] @ poses

    def track(times) -> np.ndarray:
        poses = np.asarray(original(np.asarray(times, dtype=np.float64)), dtype=np.float64)
        return track_entries(poses[:, root] @ bind_root, first, up_axis, yaw)

    return dataclasses.replace(clip, sample=sample), track
