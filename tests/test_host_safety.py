"""vbusd is safe inside a host application (issue 10 item 6): reading an asset never reloads or
edits a layer the host holds open with unsaved edits, and the warp decoder leaves warp's global
settings as the host set them, before and after decoding."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from vbusd.io import usd as usd_io

VALID = Path(__file__).parent / "fixtures" / "validate" / "valid" / "crossMatrix_float16"


@pytest.fixture
def asset_path(tmp_path):
    shutil.copytree(VALID, tmp_path / "asset")
    return tmp_path / "asset" / "asset.usda"


def test_an_open_layer_with_unsaved_edits_survives_read_asset(asset_path):
    from pxr import Sdf

    held = Sdf.Layer.FindOrOpen(str(asset_path))  # the host's layer, edited but not saved
    animation = usd_io.read_asset(asset_path).animations[0].path
    prim = held.GetPrimAtPath(animation)
    prim.SetInfo("documentation", "unsaved host edit")
    prim.attributes["vb:textureWidth"].default = 7  # were it read, the asset would be refused
    held.customLayerData = dict(held.customLayerData, host="unsaved")
    assert held.dirty
    asset = usd_io.read_asset(asset_path)
    # The host's layer: the same object, still dirty, its edits intact.
    assert Sdf.Layer.Find(str(asset_path)) is held and held.dirty
    assert held.GetPrimAtPath(animation).GetInfo("documentation") == "unsaved host edit"
    assert held.customLayerData["host"] == "unsaved"
    # vbusd read the file as saved, not the host's edits.
    assert asset.animations[0].path == animation and asset.animations[0].layout.width != 7
    assert "unsaved" not in asset_path.read_text()


def test_the_warp_decoder_leaves_warps_settings_as_the_host_set_them(asset_path):
    import warp as wp
    has_level = hasattr(wp.config, "log_level")
    if has_level:
        wp.config.log_level = host = wp.LOG_DEBUG if hasattr(wp, "LOG_DEBUG") else 0
    else:
        wp.config.quiet = host = False
    from vbusd.decoders.warp import Decoder  # importing sets nothing

    current = (lambda: wp.config.log_level) if has_level else (lambda: wp.config.quiet)
    assert current() == host
    vb = usd_io.read_asset(asset_path).animations[0]
    Decoder(vb, vb.meshes[0], device="cpu").skin(0, np.zeros(2, np.float32))
    assert current() == host  # raised for the call, restored after it
