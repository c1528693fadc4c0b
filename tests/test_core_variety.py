"""@vbusd/core's crowd variety helpers (web/core/src/variety.js, format 1.3) under Node, against values
worked out by hand: the colour of an instance is its variant's base colour times its tint, a part's
matrices lose their linear part (keeping the translation) where the mask hides the part, part bits
come from the mesh's prim name, a level's slot of a part takes the instance's matrix or its collapse by
the mask (parts on levels of detail), root motion moves a placement along its own heading, and a package's variety is read from its instance attributes,
KHR_materials_variants and the primitives' part bits (tests/node/core_variety.mjs)."""

from __future__ import annotations

import json
import subprocess

import numpy as np

from tests.helpers import node as node_tools


def test_core_variety_helpers():
    node = node_tools.require_packages()
    result = subprocess.run([node, str(node_tools.NODE_DIR / "core_variety.mjs")], capture_output=True, text=True,
                            timeout=60, cwd=node_tools.NODE_DIR)
    assert result.returncode == 0, result.stderr
    out = json.loads(result.stdout)
    # instance 0: away (0.2, 0.3, 0.8) x tint (1, 0.5, 0); 1: home 0.8 x (0.25, 1, 1); 2: no variant, white.
    np.testing.assert_allclose(out["colors"], [0.2, 0.15, 0.0, 0.2, 0.8, 0.8, 1, 1, 1], rtol=1e-6)
    assert out["bits"] == [0, 1, -1]
    hat, flag, body = (np.asarray(out[k]).reshape(3, 16) for k in ("hat", "flag", "body"))
    identity = np.eye(4).reshape(-1)
    translated = [identity.copy() for _ in range(3)]
    for i in range(3):
        translated[i][12] = i
    collapsed = [np.array([0.0] * 12 + [i, 0, 0, 1]) for i in range(3)]
    # masks 1, 0, 3: the hat (bit 0) on instances 0 and 2, the flag (bit 1) on instance 2 only.
    np.testing.assert_array_equal(hat, [translated[0], collapsed[1], translated[2]])
    np.testing.assert_array_equal(flag, [collapsed[0], collapsed[1], translated[2]])
    np.testing.assert_array_equal(body, translated)
    # Levels (spec 22.3): instance 2 (x = 2) into slot 1 with mask 1, which hides the flag (bit 1): collapsed
    # there, slot 0 untouched; with mask 3 into slot 0, the whole matrix.
    np.testing.assert_array_equal(np.asarray(out["levelSlots"][0]).reshape(2, 16), [np.zeros(16), collapsed[2]])
    np.testing.assert_array_equal(np.asarray(out["levelSlots"][1]).reshape(2, 16), [translated[2], np.zeros(16)])
    # Root motion (spec 8.5): P = T(1, 0, 0) R_y(90 deg) moved by T(0, 0, 2) in its own space: R_y(90) takes
    # +Z to +X, so the translation becomes (1 + 2, 0, 0); the rotation stays.
    np.testing.assert_allclose(out["moved"], [0, 0, -1, 0, 0, 1, 0, 0, 1, 0, 0, 0, 3, 0, 0, 1], atol=1e-7)
    assert out["variety"][0] == {"tint": [1, 0.5, 0], "variant": 1, "variantName": "away", "parts": 1,
                                 "partNames": ["Hat", "Flag"]}
    assert out["variety"][2]["variant"] == -1 and out["variety"][2]["variantName"] is None
    package = out["fromPackage"]
    assert package["variantNames"] == ["home", "away"] and package["partNames"] == ["Hat"]
    np.testing.assert_allclose(package["variantColors"], [[0.8, 0.8, 0.8], [0.2, 0.3, 0.8]])
    assert package["variant"] == [1, 0] and package["parts"] == [1, 0] and package["tint"] == [1, 1, 1, 0, 0, 1]
