"""@vbusd/core's KTX2 parser (web/core/src/ktx2.js), the one every engine's glTF loader runs.

Files written by vbusd's KTX2 writer in every texel format (format 1.2's uint32 too), with and
without Zstandard supercompression, are read under Node by the core's parser and by ktx-parse
(the parser three.js's KTX2Loader uses, an independent implementation): the container fields,
key/value keys and level bytes agree with ktx-parse's, the texels are the written ones bit for bit
and the layout is the written metadata. A damaged file is one error naming it.
"""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from vbusd.format import metadata as md
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, VirtualBones
from vbusd.io import ktx2
from vbusd.io.generator import GENERATOR

from tests.helpers import node as node_tools

pytestmark = pytest.mark.node


def make_vb(texel_format: str) -> VirtualBones:
    """Random texels of a 5-bone, 7-row texture, zero padding, two clips."""
    encoding = "compactQuatTranslation" if texel_format == "uint32" else "crossMatrix"
    layout = Layout(encoding, texel_format, 5, 7)
    rng = np.random.default_rng(11)
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    used = texels[:7, :layout.used_width]
    if texel_format in ("unorm16", "uint32"):
        used[...] = rng.integers(0, 65536 if texel_format == "unorm16" else 2**32, used.shape)
    else:
        used[...] = rng.uniform(-4, 4, used.shape)
    extra = {}
    if texel_format == "unorm16":
        lo = rng.uniform(-2, 0, (3, 4))
        extra["unorm_ranges"] = np.stack([lo, lo + 1.0], axis=-1)
    if texel_format == "uint32":
        lo = rng.uniform(-1, 0, (5, 7))
        extra["unorm_ranges"] = np.stack([lo, lo + 1.0], axis=-1)  # the compactRanges of spec 5.6
    clips = (Clip("cheer", 0, 3, 30.0, True, 0.0), Clip("idle", 3, 4, 24.0, False, 1.25))
    return VirtualBones(layout, texels, tuple(f"bone{i}" for i in range(5)), clips, **extra)


@pytest.mark.parametrize("texel_format", ["float16", "float32", "unorm16", "uint32"])
@pytest.mark.parametrize("supercompression", ["none", "zstd"])
def test_core_parser_reads_vbusd_files_as_ktx_parse_does(tmp_path, texel_format, supercompression):
    vb = make_vb(texel_format)
    text = md.dumps(md.to_dict(vb, generator=GENERATOR))
    path = tmp_path / "t.ktx2"
    path.write_bytes(ktx2.ktx2_bytes(vb.texels, text, supercompression=supercompression))
    result = node_tools.run_json("core_ktx2.mjs", path, packages=("ktx-parse", "three"))
    assert "error" not in result, result["error"]
    assert result["container"] == result["ktxParse"]
    assert result["keys"] == result["ktxParseKeys"] and "vbusd.layout" in result["keys"]
    assert result["levelsEqual"]
    assert result["layout"] == json.loads(text)
    stored = vb.texels[..., :3] if texel_format == "uint32" else vb.texels  # uint32: the three words
    assert base64.b64decode(result["texels"]) == np.ascontiguousarray(stored).tobytes()


def test_a_truncated_file_is_one_error_naming_it(tmp_path):
    vb = make_vb("float16")
    data = ktx2.ktx2_bytes(vb.texels, md.dumps(md.to_dict(vb, generator=GENERATOR)))
    path = tmp_path / "t.ktx2"
    path.write_bytes(data[:len(data) - 10])
    result = node_tools.run_json("core_ktx2.mjs", path, packages=("ktx-parse", "three"))
    assert "file.ktx2: not a KTX2 file (level 0 (bytes " in result.get("error", ""), result
