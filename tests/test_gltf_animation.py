"""glTF animation interpolation (spec Appendix C) and the accessor/topology helpers, by hand values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbusd.converters.gltf import native_rate
from vbusd.converters.gltf_animation import compose_trs, sample_channel
from vbusd.io.gltf_accessors import element_layout, triangles

S = math.sqrt(0.5)


def test_linear_vectors_and_hold():
    keys = np.array([1.0, 3.0])
    values = np.array([[0.0, 0, 0], [4.0, 2, 0]])
    got = sample_channel(np.array([0.0, 1.0, 2.0, 2.5, 3.0, 9.0]), keys, values, "LINEAR", False)
    np.testing.assert_allclose(got, [[0, 0, 0], [0, 0, 0], [2, 1, 0], [3, 1.5, 0], [4, 2, 0],
                                     [4, 2, 0]])


def test_step():
    keys = np.array([0.0, 1.0, 2.0])
    values = np.array([[1.0], [2.0], [3.0]])
    got = sample_channel(np.array([-1, 0, 0.99, 1.0, 1.5, 2.0, 5.0]), keys, values, "STEP", False)
    np.testing.assert_allclose(got[:, 0], [1, 1, 1, 2, 2, 3, 3])


def test_slerp_takes_the_shortest_path():
    # q1 = -(90 deg about z): the same rotation; shortest-path slerp halfway is 45 deg, not 135.
    keys = np.array([0.0, 1.0])
    values = np.array([[0.0, 0, 0, 1], [0.0, 0, -S, -S]])
    (q,) = sample_channel(np.array([0.5]), keys, values, "LINEAR", True)
    angle = 2 * math.atan2(abs(q[2]), abs(q[3]))
    assert angle == pytest.approx(math.pi / 4)
    # From the first key towards -q1 = +(90 deg about z): halfway is +(45 deg about z).
    np.testing.assert_allclose(q, [0, 0, math.sin(math.pi / 8), math.cos(math.pi / 8)], atol=1e-12)


def test_slerp_is_constant_speed():
    keys = np.array([0.0, 1.0])
    values = np.array([[0.0, 0, 0, 1], [0.0, 0, 1, 0]])          # 0 -> 180 deg about z
    (q,) = sample_channel(np.array([0.25]), keys, values, "LINEAR", True)
    np.testing.assert_allclose(q, [0, 0, math.sin(math.pi / 8), math.cos(math.pi / 8)], atol=1e-12)


def test_cubic_spline_hermite_with_scaled_tangents():
    # Keys 0 and 2; values 0 -> 2; out-tangent 3/s, in-tangent 0: m0 = 2 * 3 = 6, m1 = 0.
    keys = np.array([0.0, 2.0])
    values = np.array([[[0.0], [0.0], [3.0]], [[0.0], [2.0], [0.0]]])
    got = sample_channel(np.array([0.5, 1.0, 2.0, 3.0]), keys, values, "CUBICSPLINE", False)[:, 0]
    # u=0.25: 0.15625*2 + 0.140625*6 = 1.15625; u=0.5: 0.5*2 + 0.125*6 = 1.75.
    np.testing.assert_allclose(got, [1.15625, 1.75, 2.0, 2.0])


def test_cubic_spline_rotation_normalized():
    keys = np.array([0.0, 1.0])
    zero = np.zeros(4)
    values = np.array([[zero, [0, 0, 0, 1.0], zero], [zero, [0, 0, 1.0, 0], zero]])
    (q,) = sample_channel(np.array([0.5]), keys, values, "CUBICSPLINE", True)
    # Hermite with zero tangents at u=0.5 gives (0,0,0.5,0.5); normalized: 90 deg about z.
    np.testing.assert_allclose(q, [0, 0, S, S], atol=1e-12)


def test_single_key_is_constant():
    got = sample_channel(np.array([-1.0, 0.0, 4.0]), np.array([0.5]), np.array([[7.0, 8, 9]]),
                         "LINEAR", False)
    np.testing.assert_allclose(got, [[7, 8, 9]] * 3)


def test_compose_trs_order():
    # T * R * S applied to (1,0,0): scale 2 -> (2,0,0), rotate 90 about z -> (0,2,0), +(1,1,1).
    m = compose_trs(np.array([1.0, 1, 1]), np.array([0, 0, S, S]), np.array([2.0, 2, 2]))
    np.testing.assert_allclose(m @ [1, 0, 0, 1], [1, 3, 1, 1], atol=1e-12)


def test_matrix_element_layout_padding():
    # MAT3 of UNSIGNED_BYTE: 3 columns of 3 bytes each padded to 4 (glTF "Data Alignment").
    assert element_layout(5121, "MAT3")[:3] == (12, 4, 3)
    assert element_layout(5122, "MAT2")[:3] == (8, 4, 4)
    assert element_layout(5126, "MAT4")[:3] == (64, 16, 16)
    assert element_layout(5126, "VEC3")[0] == 12


def test_strip_drops_degenerate_triangles():
    # Strip 0,1,2,2,3,4: i=0 (0,1,2); i=1 (1,2,2) and i=2 (2,2,3) are degenerate and dropped;
    # i=3 is odd: (v3, v5, v4) = (2,4,3).
    got = triangles(5, np.array([0, 1, 2, 2, 3, 4]))
    np.testing.assert_array_equal(got, [[0, 1, 2], [2, 4, 3]])


@pytest.mark.parametrize("keys,rate", [
    (np.arange(49) / 24.0, 24.0), (np.arange(1, 49) / 24.0, 24.0), (np.arange(11) / 60.0, 60.0),
    (np.array([0.0, 1.25]), 30.0), (np.array([0.0, 0.1, 0.25]), 30.0), (np.array([0.0]), 30.0)])
def test_native_rate(keys, rate):
    assert native_rate(keys.astype(np.float32).astype(np.float64)) == rate


def test_step_rows_on_float32_keys_take_that_key():
    # glTF key times are float32: float32(k/24) lies up to half a float32 step above or below the
    # float64 row time k/24. A row meant to fall on key k must get key k's value (before the
    # tolerance, 17 of these 49 rows got key k-1's).
    keys = (np.arange(49, dtype=np.float32) / np.float32(24)).astype(np.float64)
    values = np.arange(49, dtype=np.float64)[:, None]
    rows = np.arange(49) / 24.0
    np.testing.assert_array_equal(sample_channel(rows, keys, values, "STEP", False)[:, 0],
                                  np.arange(49))
    # Halfway between keys STEP still holds the earlier key.
    mid = (np.arange(48) + 0.5) / 24.0
    np.testing.assert_array_equal(sample_channel(mid, keys, values, "STEP", False)[:, 0],
                                  np.arange(48))
