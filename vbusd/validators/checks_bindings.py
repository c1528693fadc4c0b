"""Checks of the prims bound to an animation: meshes (VirtualBonesBindingAPI) and point instancers
(VirtualBonesInstancingAPI).

All array checks are vectorized; each code is reported once per property with the number of
offending elements and the first one (a vertex or instance index), so a broken million-vertex
mesh gives a short report.
"""

from __future__ import annotations

import numpy as np

from vbusd.format import names as vb_names
from vbusd.format.names import ANIMATION_TYPE, BINDING_API, INSTANCING_API
from vbusd.io.usd_reader import authored_type_mismatch as wrong_type
from vbusd.io.usd_reader import read_layer_primvars, read_variety_properties
from vbusd.format.diagnostics import UsdSite, finding
from pxr import UsdGeom
from vbusd.format.compact import error_bound

__all__ = ["WEIGHT_SUM_TOLERANCE", "NORMAL_LENGTH_TOLERANCE", "INDICES", "WEIGHTS",
           "INSTANCE_PRIMVARS", "applied_schemas", "has_binding", "has_instancing",
           "check_binding_prim", "check_instancer_prim"]

WEIGHT_SUM_TOLERANCE = 1e-3
"""|sum of a vertex's weights - 1| allowed (spec/validation.md: weights may come from 8-bit glTF
weights renormalized in float32; 1e-3 is far above float32 rounding and far below a visible
shrink of a skinned vertex toward the origin)."""

NORMAL_LENGTH_TOLERANCE = 1e-3
"""| |n| - 1 | allowed for rest normals (float32 normals written by DCCs are within 1e-6)."""

INDICES = vb_names.BONE_INDICES.attribute
WEIGHTS = vb_names.BONE_WEIGHTS.attribute
INSTANCE_PRIMVARS = {p.attribute: p.type for p in vb_names.INSTANCE_PRIMVARS + vb_names.FADE_PRIMVARS}
"""Every instancing primvar, crossfade ones (format 1.1) included, with its Sdf type."""
_CLIP_PRIMVARS = (vb_names.INSTANCE_CLIP.attribute, vb_names.FADE_CLIP.attribute)
_REAL_PRIMVARS = tuple(p.attribute for p in (vb_names.INSTANCE_TIME_OFFSET, vb_names.INSTANCE_PLAYBACK_RATE,
                                             vb_names.FADE_TIME_OFFSET, vb_names.FADE_PLAYBACK_RATE,
                                             vb_names.FADE_WEIGHT))


def applied_schemas(prim) -> set:
    """API schemas applied to ``prim``, including ones whose schema is not registered."""
    names = set(prim.GetAppliedSchemas())
    listop = prim.GetMetadata("apiSchemas")
    if listop is not None:
        try:
            names.update(str(n) for n in listop.ApplyOperations([]))
        except Exception:  # a malformed list op: the registered schemas above still count
            pass
    return names


def has_binding(prim) -> bool:
    """True for prims that apply VirtualBonesBindingAPI or carry its primvars."""
    return BINDING_API in applied_schemas(prim) or prim.HasAttribute(INDICES) or prim.HasAttribute(WEIGHTS)


def has_instancing(prim) -> bool:
    """True for prims that apply VirtualBonesInstancingAPI or carry its primvars."""
    return INSTANCING_API in applied_schemas(prim) or any(prim.HasAttribute(n) for n in INSTANCE_PRIMVARS)


def _animation_target(prim, code: str, api: str):
    """The single VirtualBonesAnimation prim targeted by ``vb:animation`` (or None, findings)."""
    path = str(prim.GetPath())
    site = UsdSite(path, vb_names.ANIMATION_REL)
    relationship = prim.GetRelationship(vb_names.ANIMATION_REL)
    targets = relationship.GetTargets() if relationship.IsValid() else []
    if len(targets) != 1:
        return None, [finding(code, f"vb:animation has {len(targets)} targets; {api} needs exactly one "
                              "VirtualBonesAnimation prim", site)]
    target = prim.GetStage().GetPrimAtPath(targets[0])
    if not target or not target.IsValid():
        return None, [finding(code, f"vb:animation targets {targets[0]}, which does not exist", site)]
    if target.GetTypeName() != ANIMATION_TYPE:
        return None, [finding(code, f"vb:animation targets {targets[0]}, a {target.GetTypeName() or 'typeless'} "
                              f"prim, not a {ANIMATION_TYPE}", site)]
    return target, []


def _int_value(prim, name):
    attribute = prim.GetAttribute(name)
    if not attribute.IsValid():
        return None
    value = attribute.Get()
    return int(value) if isinstance(value, int) and not isinstance(value, bool) else None


def _array(attribute, dtype):
    value = attribute.Get()
    if value is None:
        return None
    return np.asarray(value, dtype=dtype)


def _typed_primvar(prim, name, type_name, code, out, required=True):
    attribute = prim.GetAttribute(name)
    site = UsdSite(str(prim.GetPath()), name)
    if not attribute.IsValid() or not attribute.HasValue():
        if required:
            out.append(finding(code, f"{name} ({type_name}) is missing or has no value", site))
        return None
    actual = wrong_type(attribute, type_name)
    if actual is not None:
        out.append(finding(code, f"{name} has type {actual}, expected {type_name}", site))
        return None
    return UsdGeom.Primvar(attribute)


def _unindexed(primvar, code, out):
    """The primvar, or None after a ``code`` finding when it is indexed: element ``v * K + i`` of
    the authored array is influence ``i`` of point ``v`` (spec "Mesh binding"), and readers (vbusd's
    included) refuse ``:indices``, so its values cannot be checked as if flattened."""
    if primvar is None or not primvar.IsIndexed():
        return primvar
    name = primvar.GetAttr().GetName()
    indices = primvar.GetIndicesAttr().Get()
    out.append(finding(code, f"{name} is indexed ({name}:indices holds {len(indices or ())} indices); "
                       "Virtual Bones primvars hold one value per element, unindexed",
                       UsdSite(str(primvar.GetAttr().GetPrim().GetPath()), name)))
    return None


def check_binding_prim(prim):
    """Every check of one mesh bound with VirtualBonesBindingAPI.

    Args:
        prim: A ``Usd.Prim`` (normally a Mesh) applying the API or carrying its primvars.
    """

    out = []
    path = str(prim.GetPath())
    if BINDING_API not in applied_schemas(prim):
        out.append(finding("binding.api.missing", f"{path} has vb: binding primvars but does not apply "
                           f"{BINDING_API}", UsdSite(path)))
    elif not prim.IsA(UsdGeom.Mesh):
        out.append(finding("binding.api.prim", f"{BINDING_API} is applied to a "
                           f"{prim.GetTypeName() or 'typeless'} prim; it applies to Mesh prims only",
                           UsdSite(path)))
    target, problems = _animation_target(prim, "binding.animation", BINDING_API)
    out += problems
    bone_count = _int_value(target, vb_names.BY_KEY["boneCount"].name) if target is not None else None

    points_attr = UsdGeom.Mesh(prim).GetPointsAttr() if prim.IsA(UsdGeom.PointBased) else prim.GetAttribute("points")
    points = _array(points_attr, np.float64) if points_attr and points_attr.IsValid() else None
    if points is not None:
        points = points.reshape(-1, 3) if points.size % 3 == 0 else None
    out += _check_topology(prim, path, points)
    if points is not None:
        bad = ~np.all(np.isfinite(points), axis=-1)
        if bad.any():
            first = int(np.argmax(bad))
            out.append(finding("binding.points.nonFinite", f"{int(bad.sum())} rest point(s) are NaN or infinite; "
                               f"the first is point {first} = {points[first].tolist()}", UsdSite(path, "points")))

    indices_pv = _unindexed(_typed_primvar(prim, INDICES, "int[]", "binding.primvar.missing", out),
                            "binding.primvar.indexed", out)
    weights_pv = _unindexed(_typed_primvar(prim, WEIGHTS, "float[]", "binding.primvar.missing", out),
                            "binding.primvar.indexed", out)
    sizes = {}
    for name, primvar in ((INDICES, indices_pv), (WEIGHTS, weights_pv)):
        if primvar is None:
            continue
        interpolation = primvar.GetInterpolation()
        if interpolation != UsdGeom.Tokens.vertex:
            out.append(finding("binding.interpolation", f"{name} has interpolation {interpolation!r}; "
                               "it must be 'vertex' (K values per point)", UsdSite(path, name)))
        sizes[name] = primvar.GetElementSize()
    if len(sizes) == 2 and sizes[INDICES] != sizes[WEIGHTS]:
        out.append(finding("binding.elementSize", f"elementSize is {sizes[INDICES]} for {INDICES} but "
                           f"{sizes[WEIGHTS]} for {WEIGHTS}", UsdSite(path, WEIGHTS)))
        return out
    k = next(iter(sizes.values())) if sizes else None
    if k is not None and k < 1:
        out.append(finding("binding.elementSize", f"elementSize is {k}; at least 1", UsdSite(path, INDICES)))
        return out
    vertex_count = None if points is None else len(points)
    arrays = {}
    for name, primvar, dtype in ((INDICES, indices_pv, np.int64), (WEIGHTS, weights_pv, np.float64)):
        if primvar is None:
            continue
        values = _array(primvar.GetAttr(), dtype)
        if values is None:
            continue
        if vertex_count is not None and len(values) != vertex_count * k:
            out.append(finding("binding.count", f"{name} holds {len(values)} values; {vertex_count} points x "
                               f"elementSize {k} = {vertex_count * k} expected", UsdSite(path, name)))
            continue
        if len(values) % k:
            out.append(finding("binding.count", f"{name} holds {len(values)} values, not a multiple of "
                               f"elementSize {k}", UsdSite(path, name)))
            continue
        arrays[name] = values.reshape(-1, k)
    if INDICES in arrays and bone_count is not None:
        idx = arrays[INDICES]
        bad = (idx < 0) | (idx >= bone_count)
        if bad.any():
            vertex, slot = np.unravel_index(int(np.argmax(bad)), bad.shape)
            out.append(finding("binding.indices.range", f"{int(bad.sum())} bone index(es) outside 0.."
                               f"{bone_count - 1}; the first is {int(idx[vertex, slot])} at vertex {vertex}, "
                               f"influence {slot}", UsdSite(path, INDICES)))
    if WEIGHTS in arrays:
        w = arrays[WEIGHTS]
        bad = ~np.isfinite(w) | (w < 0)
        if bad.any():
            vertex, slot = np.unravel_index(int(np.argmax(bad)), bad.shape)
            out.append(finding("binding.weights.negative", f"{int(bad.sum())} weight(s) are negative or not "
                               f"finite; the first is {float(w[vertex, slot])} at vertex {vertex}, influence "
                               f"{slot}", UsdSite(path, WEIGHTS)))
        sums = np.sum(np.where(np.isfinite(w), w, 0.0), axis=1)
        off = np.abs(sums - 1.0) > WEIGHT_SUM_TOLERANCE
        if off.any():
            vertex = int(np.argmax(off))
            out.append(finding("binding.weights.sum", f"{int(off.sum())} vertex(es) have weights not summing "
                               f"to 1 (tolerance {WEIGHT_SUM_TOLERANCE}); the first is vertex {vertex} with "
                               f"sum {float(sums[vertex]):.6g}", UsdSite(path, WEIGHTS)))
    out += _check_normals(prim, path)
    if target is not None and points is not None and INDICES in arrays and WEIGHTS in arrays and bone_count:
        out += _check_compact_error_bound(target, path, points, arrays[INDICES], arrays[WEIGHTS], bone_count)
    return out


COMPACT_ERROR_FRACTION = 5e-5
"""The compact encoding's accuracy target (issue 26): 5e-5 of the mesh's bounding-box diagonal."""


def _check_compact_error_bound(target, path, points, indices, weights, bone_count):
    """``encoding.compact.errorBound``: the first-order quantization error bound of spec 5.6.3 for each
    bone of a compactQuatTranslation animation, at the farthest rest point it moves, against 5e-5 of
    the mesh's bounding-box diagonal (a warning: the bound is above what decoders measure)."""

    if target.GetAttribute(vb_names.BY_KEY["texelFormat"].name).Get() != "uint32":
        return []
    low = _array(target.GetAttribute(vb_names.COMPACT_RANGE_MIN), np.float64)
    high = _array(target.GetAttribute(vb_names.COMPACT_RANGE_MAX), np.float64)
    if low is None or high is None or low.size != 7 * bone_count or high.size != low.size:
        return []  # reported by the animation prim's own checks
    ranges = np.stack([low.reshape(-1, 7), high.reshape(-1, 7)], axis=-1)
    if not np.all(np.isfinite(points)) or not len(points):
        return []
    radius = np.zeros(bone_count)
    distance = np.linalg.norm(points, axis=1)
    valid = (indices >= 0) & (indices < bone_count) & (weights > 0)
    for k in range(indices.shape[1]):
        np.maximum.at(radius, indices[valid[:, k], k], distance[valid[:, k]])
    bound = error_bound(ranges, radius)
    diagonal = float(np.linalg.norm(np.ptp(points, axis=0))) or 1.0
    bone = int(np.argmax(bound))
    if bound[bone] <= COMPACT_ERROR_FRACTION * diagonal:
        return []
    return [finding("encoding.compact.errorBound", f"bone {bone}'s compact quantization error bound is "
                    f"{bound[bone]:.3g} at its farthest point ({radius[bone]:.4g} from the origin), "
                    f"{bound[bone] / diagonal:.3g} of the mesh's diagonal {diagonal:.4g} (target "
                    f"{COMPACT_ERROR_FRACTION:g}); ranges per bone and clip or another encoding are more exact",
                    UsdSite(path, "points"))]


def _check_topology(prim, path, points):
    """``binding.mesh``: skinning needs the rest points, and face-varying normals need a valid
    face list (vbusd's reader refuses a bound mesh without them)."""
    if points is None:
        return [finding("binding.mesh", "the bound mesh has no readable points (point3f[], 3 values "
                        "per point)", UsdSite(path, "points"))]
    if not prim.HasAttribute("faceVertexCounts") and not prim.HasAttribute("faceVertexIndices"):
        return []  # not a Mesh (binding.api.prim says so) or a point cloud: nothing more to check
    counts = _array(prim.GetAttribute("faceVertexCounts"), np.int64)
    indices = _array(prim.GetAttribute("faceVertexIndices"), np.int64)
    if counts is None or indices is None:
        missing = "faceVertexCounts" if counts is None else "faceVertexIndices"
        return [finding("binding.mesh", f"the bound mesh has no {missing}", UsdSite(path, missing))]
    if counts.size and counts.min() < 3:
        face = int(np.argmax(counts < 3))
        return [finding("binding.mesh", f"face {face} has {int(counts[face])} vertices; at least 3",
                        UsdSite(path, "faceVertexCounts"))]
    if int(counts.sum()) != len(indices):
        return [finding("binding.mesh", f"faceVertexCounts sum to {int(counts.sum())} but there are "
                        f"{len(indices)} faceVertexIndices", UsdSite(path, "faceVertexCounts"))]
    bad = (indices < 0) | (indices >= len(points))
    if bad.any():
        first = int(np.argmax(bad))
        return [finding("binding.mesh", f"{int(bad.sum())} faceVertexIndices outside 0..{len(points) - 1}; "
                        f"the first is {int(indices[first])} at face-vertex {first}",
                        UsdSite(path, "faceVertexIndices"))]
    return []


def _check_normals(prim, path):
    attribute, name = None, None
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    if primvar and primvar.HasValue():
        attribute, name = primvar.GetAttr(), "primvars:normals"
    elif prim.HasAttribute("normals") and prim.GetAttribute("normals").HasValue():
        attribute, name = prim.GetAttribute("normals"), "normals"
    if attribute is None:
        return []
    normals = _array(attribute, np.float64)
    if normals is None or normals.size % 3:
        return []
    normals = normals.reshape(-1, 3)
    out = []
    # Skinning gives normal j the influences of point j (vertex) or of face-vertex j's point
    # (faceVarying, spec "Mesh binding"): any other interpolation or count leaves normals unskinned.
    if name == "primvars:normals":
        interpolation = str(primvar.GetInterpolation())
        count = len(primvar.ComputeFlattened() or ())
    else:
        interpolation = str(UsdGeom.PointBased(prim).GetNormalsInterpolation()) \
            if prim.IsA(UsdGeom.PointBased) else "vertex"
        count = len(normals)
    points = _array(prim.GetAttribute("points"), np.float64) if prim.HasAttribute("points") else None
    points = None if points is None else points.reshape(-1, 3)
    face_vertices = prim.GetAttribute("faceVertexIndices").Get() if prim.HasAttribute("faceVertexIndices") \
        else None
    expected = {"vertex": None if points is None else len(points),
                "faceVarying": None if face_vertices is None else len(face_vertices)}
    if interpolation not in expected:
        out.append(finding("binding.normals.count", f"{name} has interpolation {interpolation!r}; rest "
                           "normals must be 'vertex' or 'faceVarying'", UsdSite(path, name)))
    elif expected[interpolation] is not None and count != expected[interpolation]:
        what = "points" if interpolation == "vertex" else "face-vertices"
        out.append(finding("binding.normals.count", f"{name} holds {count} {interpolation} normals for "
                           f"{expected[interpolation]} {what}", UsdSite(path, name)))
    nonfinite = ~np.all(np.isfinite(normals), axis=-1)
    if nonfinite.any():
        first = int(np.argmax(nonfinite))
        return out + [finding("binding.normals.nonFinite", f"{int(nonfinite.sum())} rest normal(s) are NaN or "
                              f"infinite; the first is normal {first} = {normals[first].tolist()}",
                              UsdSite(path, name))]
    length = np.linalg.norm(normals, axis=-1)
    bad = ~(np.abs(length - 1.0) <= NORMAL_LENGTH_TOLERANCE)
    if not bad.any():
        return out
    first = int(np.argmax(bad))
    return out + [finding("binding.normals.unit", f"{int(bad.sum())} rest normal(s) are not unit length (tolerance "
                    f"{NORMAL_LENGTH_TOLERANCE}); the first is normal {first} with length {float(length[first]):.6g}",
                    UsdSite(path, name))]


class _LayerProblem(Exception):
    pass


def _layer_findings(prim, target, count: int, clip_count: int) -> list:
    """The first problem of the format 1.2 layer primvars, as the readers find it
    (:func:`vbusd.io.usd_reader.read_layer_primvars`): they refuse the crowd on it."""
    names_attribute = target.GetAttribute(vb_names.MASK_NAMES)
    mask_names = names_attribute.Get() if names_attribute.IsValid() and names_attribute.HasAuthoredValue() else None
    found = []

    def fail(code, message, site):
        found.append(finding(code, message, site))
        raise _LayerProblem

    try:
        read_layer_primvars(prim, count, clip_count, len(mask_names or ()), fail)
    except _LayerProblem:
        pass
    return found


def _variety_findings(prim, count: int) -> list:
    """The first problem of the format 1.3 variety properties, as the readers find it
    (:func:`vbusd.io.usd_reader.read_variety_properties`): they refuse the crowd on it."""
    found = []

    def fail(code, message, site):
        found.append(finding(code, message, site))
        raise _LayerProblem

    try:
        read_variety_properties(prim, count, fail)
    except _LayerProblem:
        pass
    return found


def check_instancer_prim(prim):
    """Every check of one point instancer with VirtualBonesInstancingAPI."""

    out = []
    path = str(prim.GetPath())
    target, problems = _animation_target(prim, "instancer.animation", INSTANCING_API)
    out += problems
    clip_count = None
    if target is not None:
        clip_names = target.GetAttribute(vb_names.CLIP_BY_KEY["name"].name)
        value = clip_names.Get() if clip_names.IsValid() else None
        clip_count = None if value is None else len(value)
    # One instance per position (spec "Instancing": vertex primvars hold as many values as
    # positions); without positions the instance count is unknown.
    count = None
    attribute = prim.GetAttribute("positions")
    if attribute.IsValid() and attribute.HasValue():
        count = len(attribute.Get())
    else:
        out.append(finding("instancer.count", "positions is missing: the instances are the positions",
                           UsdSite(path, "positions")))
    arrays = {}
    for name, type_name in INSTANCE_PRIMVARS.items():
        # Unauthored instancing primvars take their defaults (clip 0, offset 0, rate 1; spec
        # "Instancing"), so only authored ones are checked.
        primvar = _unindexed(_typed_primvar(prim, name, type_name, "instancer.count", out, required=False),
                             "instancer.indexed", out)
        if primvar is None:
            continue
        site = UsdSite(path, name)
        interpolation = primvar.GetInterpolation()
        if interpolation != UsdGeom.Tokens.vertex:
            out.append(finding("instancer.count", f"{name} has interpolation {interpolation!r}; it must be "
                               "'vertex' (one value per instance)", site))
            continue
        if primvar.GetElementSize() != 1:
            out.append(finding("instancer.count", f"{name} has elementSize {primvar.GetElementSize()}; it "
                               "must be 1 (one value per instance)", site))
            continue
        values = _array(primvar.GetAttr(), np.float64)
        if values is None:
            continue
        if count is not None and len(values) != count:
            out.append(finding("instancer.count", f"{name} holds {len(values)} values for {count} instances",
                               site))
            continue
        arrays[name] = values
    for name in _CLIP_PRIMVARS:
        clips = arrays.get(name)
        if clips is None or clip_count is None:
            continue
        bad = (clips < 0) | (clips >= clip_count)
        if bad.any():
            first = int(np.argmax(bad))
            out.append(finding("instancer.clip.range", f"{int(bad.sum())} instance(s) play a clip outside "
                               f"0..{clip_count - 1}; the first is instance {first} with clip {int(clips[first])}",
                               UsdSite(path, name)))
    for name in _REAL_PRIMVARS:
        values = arrays.get(name)
        if values is None:
            continue
        bad = ~np.isfinite(values)
        if bad.any():
            first = int(np.argmax(bad))
            out.append(finding("instancer.nonFinite", f"{int(bad.sum())} value(s) are NaN or infinite; the first "
                               f"is instance {first} with {float(values[first])}", UsdSite(path, name)))
    if count is not None and clip_count is not None:
        out += _layer_findings(prim, target, count, clip_count)
    if count is not None:
        out += _variety_findings(prim, count)
    fading = [p.attribute for p in vb_names.FADE_PRIMVARS
              if prim.GetAttribute(p.attribute).IsValid() and prim.GetAttribute(p.attribute).HasAuthoredValue()]
    if fading and target is not None:
        # Spec "Instancing": a crossfading instancer binds a format 1.1 animation, so that a 1.0
        # reader refuses it instead of silently playing the first clip alone.
        minor = target.GetAttribute(vb_names.BY_KEY["formatMinorVersion"].name)
        value = minor.Get() if minor.IsValid() and minor.HasAuthoredValue() else 0
        if not isinstance(value, int) or value < 1:
            out.append(finding("instancer.fade.version", f"{', '.join(fading)} (format 1.1 crossfade) on an "
                               f"instancer whose animation {target.GetPath()} is format 1.{value or 0}; set "
                               f"{vb_names.BY_KEY['formatMinorVersion'].name} = 1 there", UsdSite(path, fading[0])))
    weights = arrays.get(vb_names.FADE_WEIGHT.attribute)
    if weights is not None:
        # Spec "Instancing" (format 1.1 crossfade): weights lie in [0, 1]; decoders clamp the others.
        outside = np.isfinite(weights) & ((weights < 0) | (weights > 1))
        if outside.any():
            first = int(np.argmax(outside))
            out.append(finding("instancer.fadeWeight.range", f"{int(outside.sum())} fade weight(s) outside [0, 1]; "
                               f"the first is instance {first} with {float(weights[first]):g} (decoders clamp it)",
                               UsdSite(path, vb_names.FADE_WEIGHT.attribute)))
    return out
