"""Texel checks against independent facts: IEEE rounding bounds, hand-made clips.

The tolerance of the unit-length and orthogonality checks is derived in spec/validation.md
("Tolerances"). These tests check the derivation itself with random rotations rounded by numpy
(the rounding error must stay within the proven bound 2u + u^2, and the checks must accept it),
and that an error a few times larger is caught.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbusd.format.layout import Layout
from vbusd.validators import checks_texels as ct


def _random_rotations(n, rng):
    # Written out rather than vbusd.format.encoding.quat_to_matrix: the inputs of these tests must not
    # depend on the package under test.
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def _cross_texture(rotations, dtype, bones):
    """(rows, bones) rotations -> a crossMatrix texture (columns: x axis, y axis, translation)."""
    rows = rotations.shape[0]
    layout = Layout("crossMatrix", {"float16": "float16", "float32": "float32"}[dtype], bones, rows)
    tex = np.zeros(layout.shape, dtype=dtype)
    data = np.zeros((rows, bones, 3, 4))
    data[..., 0, :3] = rotations[..., :, 0]
    data[..., 1, :3] = rotations[..., :, 1]
    data[..., 2, :3] = 0.25
    data[..., 3] = 1.0
    tex[:, :layout.used_width] = data.reshape(rows, bones * 3, 4).astype(dtype)
    return tex, layout


@pytest.mark.parametrize("dtype,u", [("float16", 2.0 ** -11), ("float32", 2.0 ** -24)])
def test_rounded_rotations_stay_within_the_derived_bound_and_pass(dtype, u):
    rng = np.random.default_rng(7)
    rotations = _random_rotations(64 * 50, rng).reshape(64, 50, 3, 3)
    tex, layout = _cross_texture(rotations, dtype, 50)
    data = tex[:, :150].astype(np.float64).reshape(64, 50, 3, 4)
    x, y = data[..., 0, :3], data[..., 1, :3]
    assert np.max(np.abs(np.linalg.norm(x, axis=-1) - 1)) <= u * (1 + 1e-9)
    assert np.max(np.abs(np.sum(x * y, axis=-1))) <= 2 * u + u * u
    assert ct.check_encoding(tex, "t.exr", layout) == []


def test_an_axis_a_few_ulps_too_long_is_caught_at_the_worst_bone_and_row():
    rng = np.random.default_rng(3)
    rotations = _random_rotations(8 * 6, rng).reshape(8, 6, 3, 3)
    tex, layout = _cross_texture(rotations, "float16", 6)
    tex[2, 3 * 4 + 1, :3] *= np.float16(1 + 6 * 2.0 ** -11)   # bone 4, y axis, row 2: 6u too long
    tex[5, 3 * 1 + 0, :3] *= np.float16(1 + 12 * 2.0 ** -11)  # bone 1, x axis, row 5: 12u (worst)
    [found] = ct.check_encoding(tex, "t.exr", layout)
    assert found.code == "encoding.crossMatrix.orthonormal"
    assert (found.location.row, found.location.bone, found.location.texel) == (5, 1, 0)
    assert "at 2 bone-row(s)" in found.message


def test_tolerances_match_the_spec_formulae():
    assert ct.tolerance("float16") == 4 * 2.0 ** -11
    assert ct.tolerance("float32") == pytest.approx(4 * 2.0 ** -24 + 1e-6)
    ranges = np.zeros((3, 4, 2))
    ranges[..., 0], ranges[..., 1] = -1.0, 1.0
    assert ct.tolerance("unorm16", ranges) == pytest.approx(4 * math.sqrt(3) * (2 / 65535 / 2) + 1e-7)



def test_padding_minus_zero_and_first_address():
    layout = Layout("quatTranslation", "float16", 3, 5, "powerOfTwo", "powerOfTwo")  # 6 -> 8 cols, 5 -> 8 rows
    tex = np.zeros(layout.shape, np.float16)
    assert ct.check_padding(tex, "t.exr", layout) == []
    tex[6, 2, 1] = np.float16(-0.0)  # a padding row
    tex[1, 7, 3] = np.float16(2.0)   # a padding column
    [found] = ct.check_padding(tex, "t.exr", layout)
    assert found.code == "texture.padding.nonZero" and "2 padding channel" in found.message
    loc = found.location
    assert (loc.row, loc.column, loc.bone, loc.channel) == (1, 7, None, 3)


def test_non_finite_reports_count_and_first_texel():
    layout = Layout("crossMatrix", "float32", 2, 4, "none")
    tex = np.zeros(layout.shape, np.float32)
    tex[3, 4, 2] = np.inf
    tex[1, 5, 0] = np.nan
    [found] = ct.check_non_finite(tex, "t.exr", layout)
    loc = found.location
    assert (loc.row, loc.column, loc.bone, loc.texel, loc.channel) == (1, 5, 1, 2, 0)
    assert found.message.startswith("2 channel value(s)")


def _quat_texture(quats, scales=None):
    rows, bones = quats.shape[:2]
    layout = Layout("quatTranslation", "float32", bones, rows, "none")
    tex = np.zeros(layout.shape, np.float32)
    data = np.zeros((rows, bones, 2, 4), np.float32)
    data[..., 0, :] = quats
    data[..., 1, 3] = 1.0 if scales is None else scales
    tex[:] = data.reshape(rows, bones * 2, 4)
    return tex, layout


def test_quaternion_hemisphere_and_loop_jump_on_hand_made_clips():
    angles = np.linspace(0, 1.4, 8)  # a swing about z, not periodic
    q = np.zeros((8, 2, 4))
    q[:, :, 2] = np.sin(angles / 2)[:, None]
    q[:, :, 3] = np.cos(angles / 2)[:, None]
    tex, layout = _quat_texture(q)
    loop = [{"name": "swing", "firstRow": 0, "rowCount": 8, "loop": True}]
    clamp = [dict(loop[0], loop=False)]
    assert ct.check_encoding(tex, "t.exr", layout, clips=clamp) == []
    [jump] = ct.check_loop_jumps(tex, "t.exr", layout, clips=loop)
    assert jump.code == "clip.loopJump" and jump.location.row == 7
    assert ct.check_loop_jumps(tex, "t.exr", layout, clips=clamp) == []
    periodic = np.zeros((8, 2, 4))
    phase = 0.3 * np.sin(2 * np.pi * np.arange(8) / 8)
    periodic[:, :, 2], periodic[:, :, 3] = np.sin(phase)[:, None], np.cos(phase)[:, None]
    tex_p, _ = _quat_texture(periodic)
    assert ct.check_loop_jumps(tex_p, "t.exr", layout, clips=loop) == []
    flipped = q.copy()
    flipped[4, 1] *= -1
    tex_f, _ = _quat_texture(flipped)
    [hemi] = ct.check_encoding(tex_f, "t.exr", layout, clips=clamp)
    assert hemi.code == "encoding.quat.hemisphere" and (hemi.location.row, hemi.location.bone) == (4, 1)


def test_dual_quaternion_rigidity_scales_with_translation():
    layout = Layout("dualQuat", "float16", 1, 2, "none")
    tex = np.zeros(layout.shape, np.float16)
    t = np.array([300.0, -200.0, 100.0])  # large translation: |q_d| = |t| / 2 = 187
    # q_r = identity (0, 0, 0, 1); q_d = 0.5 * (t, 0) * q_r = (t / 2, 0)
    tex[:, 0] = (0, 0, 0, 1)
    tex[:, 1, :3] = (t / 2).astype(np.float16)
    assert ct.check_encoding(tex, "t.exr", layout) == []  # float16 rounding of 150 is 0.0625
    tex[1, 1, 3] = np.float16(2.0)  # w of the dual part: q_r . q_d = 2, relative 2 / 187 > 4u
    [found] = ct.check_encoding(tex, "t.exr", layout)
    assert found.code == "encoding.dualQuat.orthogonal" and found.location.row == 1
