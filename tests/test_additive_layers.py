"""Additive layers stored in a crowd (format 1.3, spec/virtual-bones.md 23.4): the instancer's
primvars:vb:layerMode, layerReferenceClip and layerReferenceTime written, read back equal, validated
clean, decoded from the file as from the model (and as vbusd.skin with the same layers given by hand),
and bad values refused with their codes at their primvar."""

from __future__ import annotations

import numpy as np
import pytest

import vbusd
from vbusd.decoders.reference import skin_crowd

from tests.helpers.crowds import ADDITIVE_ROWS, additive_chain


@pytest.fixture(scope="module")
def additive(tmp_path_factory):
    return additive_chain(tmp_path_factory.mktemp("additive"))


def test_additive_layers_round_trip_through_usd_primvars(additive):
    from pxr import Usd

    stage = Usd.Stage.Open(str(additive))
    prim = stage.GetPrimAtPath("/Chain/Crowd")
    assert list(prim.GetAttribute("primvars:vb:layerMode").Get()) == [1, 0, 1, 0, 0, 1, 1, 1]
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 3
    assert vbusd.validate(additive).valid
    asset = vbusd.read_asset(additive)
    vb, crowd = asset.animations[0], asset.crowds[0]
    clips = [c.name for c in vb.clips]
    np.testing.assert_array_equal(crowd.layer_mode, [[r[5] for r in row[3]] for row in ADDITIVE_ROWS])
    np.testing.assert_array_equal(crowd.layer_reference_clip, [[clips.index(r[6]) for r in row[3]] for row in ADDITIVE_ROWS])
    np.testing.assert_allclose(crowd.layer_reference_time, [[r[7] for r in row[3]] for row in ADDITIVE_ROWS])
    t = 0.45
    decoded, _ = skin_crowd(vb, vb.meshes[0], crowd, t)
    for i, (clip, offset, rate, layers) in enumerate(ADDITIVE_ROWS):
        f32 = lambda v: float(np.float32(v))  # noqa: E731  (the crowd holds float32)
        given = [{"clip": c, "time": f32(o) + f32(r) * t, "weight": f32(w), "mask": m,
                  **({"mode": "additive", "reference": {"clip": rc, "time": f32(rt)}} if mode else {})}
                 for c, o, r, w, m, mode, rc, rt in layers if w > 0]
        ours = vbusd.skin(vb, clip, f32(offset) + f32(rate) * t, layers=given)[0].points + crowd.positions[i]
        diagonal = float(np.linalg.norm(ours.max(axis=0) - ours.min(axis=0)))
        assert float(np.abs(decoded[i] - ours).max()) <= 1e-7 * diagonal, i
        if any(layer[5] == 1 and layer[3] > 0 for layer in layers):  # the additive layer matters
            plain = vbusd.skin(vb, clip, f32(offset) + f32(rate) * t,
                               layers=[g for g in given if g.get("mode") != "additive"])[0].points + crowd.positions[i]
            assert float(np.abs(plain - ours).max()) > 1e-3 * diagonal, i


@pytest.mark.parametrize("edit, code, attribute", [
    ("mode", "layers.mode", "primvars:vb:layerMode"),
    ("reference", "instancer.clip.range", "primvars:vb:layerReferenceClip"),
    ("version", "format.version", "primvars:vb:layerMode"),
])
def test_bad_additive_primvars_are_findings_at_their_primvar(additive, tmp_path, edit, code, attribute):
    import shutil

    from pxr import Usd, Vt

    folder = tmp_path / "bad"
    shutil.copytree(additive.parent, folder)
    path = folder / additive.name
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Chain/Crowd")
    if edit == "mode":
        prim.GetAttribute("primvars:vb:layerMode").Set(Vt.IntArray([1, 0, 2, 0, 0, 1, 1, 1]))
    elif edit == "reference":
        prim.GetAttribute("primvars:vb:layerReferenceClip").Set(Vt.IntArray([2, 1, 0, 0, 1, 7, 0, 1]))
    else:
        prim.RemoveProperty("vb:formatMinorVersion")
    stage.GetRootLayer().Save()
    report = vbusd.validate(path)
    found = [(f.code, f.location.property) for f in report.findings if f.code == code]
    assert found == [(code, attribute)], [(f.code, str(f.location)) for f in report.findings]
    with pytest.raises(vbusd.VbusdError, match=code.replace(".", r"\.")):
        vbusd.read_asset(path)


def test_a_1_2_reader_refuses_additive_layers_by_name(additive, monkeypatch):
    """Spec 23.4: the instancer states vb:formatMinorVersion 3, so a 1.2 reader refuses the crowd and
    names the additive primvars rather than play the layers as override ones."""
    from vbusd.format import versioning

    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 2))
    with pytest.raises(vbusd.VbusdError) as error:
        vbusd.read_asset(additive)
    message = str(error.value)
    assert "format.version" in message and "newer than this reader (version 1.2)" in message
    assert "primvars:vb:layerMode" in message and "primvars:vb:layerReferenceTime" in message
