"""Small animations written from code in vbusd's own model (:mod:`vbusd.format.model`), shared by
the shader, crossfade, root-motion and conformance tests."""

from __future__ import annotations

import math

import numpy as np

from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh


def rotation(axis, angle):
    """The 3x3 rotation of ``angle`` radians about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
                     [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
                     [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)]])


def chain_animation(scaled: bool, twist: bool = False) -> SkinnedAnimation:
    """A 5-bone chain with a looping 2 s clip and a clamped 1 s clip; random 6-influence weights.

    ``twist`` turns bones 3 and 4 by a further 198 degrees, so that many vertices blend
    quaternions of opposite hemispheres (dot < 0 with the first influence): the only data on which
    dual-quaternion skinning's sign flip matters.
    """
    rng = np.random.default_rng(7)
    axes = rng.normal(size=(5, 3))
    twist_matrix = np.eye(4)
    twist_matrix[:3, :3] = rotation([0.3, 0.2, 1.0], 1.1 * math.pi)

    def make_sampler(speed, duration):
        def sample(times):
            times = np.clip(np.atleast_1d(times), 0.0, duration)
            out = np.tile(np.eye(4), (len(times), 5, 1, 1))
            for k, time in enumerate(times):
                world = np.eye(4)
                for bone in range(5):
                    local = np.eye(4)
                    local[:3, :3] = rotation(axes[bone], 0.9 * math.sin(2 * math.pi * speed * time / duration + bone))
                    if scaled:
                        local[:3, :3] *= 1.0 + 0.2 * math.sin(time + bone)
                    local[:3, 3] = (0, 0.5 if bone else 0, 0)
                    world = world @ local
                    bind = np.eye(4)
                    bind[1, 3] = -0.5 * bone
                    out[k, bone] = world @ bind
            if twist:
                out[:, 3:] = out[:, 3:] @ twist_matrix
            return out
        return sample

    points = rng.uniform(-0.3, 0.3, size=(24, 3)) + np.array([0, 1.0, 0])
    normals = rng.normal(size=(24, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[5] = 0.0  # a degenerate normal (meshes have them): the spec's normalize(0) is 0, not NaN
    indices = np.stack([rng.permutation(5)[:5].tolist() + [int(rng.integers(5))] for _ in range(24)])
    weights = rng.uniform(0.05, 1.0, size=(24, 6))
    weights /= weights.sum(axis=1, keepdims=True)
    mesh = SkinnedMesh("/Chain/Mesh", points, np.full(8, 3), np.arange(24), indices, weights, normals=normals)
    clips = (AnimationClip("wave", 0.0, 2.0, make_sampler(1, 2.0), native_rate=15, loop=True),
             AnimationClip("bend", 0.0, 1.0, make_sampler(0.5, 1.0), native_rate=10, loop=False))
    return SkinnedAnimation("Anim", "/Chain/Anim", tuple(f"b{i}" for i in range(5)), clips, (mesh,))


def loop_walk(yaw_rate: float):
    """A 1 s loop walking 1.5 m/s along +Z (turning ``yaw_rate`` rad/s), one bone, bind at the origin."""
    def sample(times):
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        out = np.tile(np.eye(4), (len(times), 1, 1, 1))
        for k, t in enumerate(times):
            c, s = math.cos(yaw_rate * t), math.sin(yaw_rate * t)
            out[k, 0, :3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
            out[k, 0, :3, 3] = (0.0, 0.1 * math.sin(2 * math.pi * t), 1.5 * t)
        return out

    mesh = SkinnedMesh("/Walk/Mesh", np.array([[0.0, 1.0, 0.0], [0.2, 0.0, 0.1]]), np.array([2]), np.array([0, 1]),
                       np.array([[0], [0]]), np.array([[1.0], [1.0]]))
    clip = AnimationClip("walk", 0.0, 1.0, sample, native_rate=30, loop=True)
    return SkinnedAnimation("Walk", "/Walk/Anim", ("hips",), (clip,), (mesh,), bind_transforms=np.eye(4)[None])
