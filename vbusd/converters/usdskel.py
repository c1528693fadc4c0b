"""UsdSkel converter: read skinned meshes and skeleton animation from a USD stage.

The mapping is normative in spec/usd-conversion.md; in short:

* one :class:`~vbusd.format.model.SkinnedAnimation` per bound Skeleton, written at the Skeleton's prim
  path, with the Skeleton's joints as bones in their order;
* bones are UsdSkel's skinning transforms carried into the stage's *world space*:
  ``M_j(t) = (S_j(t) * W_skel(t))^T`` in USD row-vector terms, where ``S_j`` is
  ``SkeletonQuery.ComputeSkinningTransforms`` (``inverse(bind_j) * jointSkel_j``) and ``W_skel`` the
  Skeleton prim's local-to-world transform (SkelRoot, ancestors and the Skeleton's own ops, animated
  or not), so decoded points equal UsdSkel's skinned points placed in the world;
* rest points are the mesh points with ``primvars:skel:geomBindTransform`` applied (bind space);
  the skinned mesh's own transform is ignored, as UsdSkel ignores it;
* mesh-local ``skel:joints`` are remapped to skeleton order; constant (rigid) influences are
  repeated for every point, also for gprims that inherit them from an Xform above; rigidly bound
  Cube/Sphere/Cylinder/Cone/Capsule prims become tessellated meshes; meshes under the SkelRoot that
  no binding reaches follow their own transform as extra bones; weights are normalized (UsdSkel
  does not: a warning says so);
* one clip per skeleton, from the first to the last time sample of the animation and of the
  skeleton's transforms (or ``ReadOptions.time_range``), sampled as UsdSkel samples it (USD's own
  interpolation between samples): all frames at once by :class:`AllFramesSkinning` (UsdSkel's
  arithmetic vectorized over frames, checked against ``ComputeSkinningTransforms``), or frame by
  frame through UsdSkel where that class cannot answer.

UsdSkel only warns (or stays silent) on malformed data; every rule it relies on is checked here
first and reported as one :class:`~vbusd.format.errors.InputError` naming the prim.
"""

from __future__ import annotations

import dataclasses

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from vbusd.format.encoding import all_finite
from vbusd.format.errors import InputError, OptionsError, UnsupportedError
from vbusd.format.model import AnimationClip, ReadOptions, SkinnedAnimation, SkinnedMesh, SourceScene
from pxr import Usd, UsdGeom, UsdSkel
from vbusd.format.diagnostics import Diagnostics
from vbusd.io.usd_reader import open_stage
from vbusd.format.layout import MAX_TEXTURE_DIMENSION, Encoding
from pxr import Sdf
from vbusd.kernels import bake as bake_kernels
from vbusd.io.usd_reader import captured_usd_diagnostics
from pxr import Tf
from vbusd.io.usd_reader import tf_message
from vbusd.io.usd_lod import levels_of
from pxr import Vt
from pxr import Gf

__all__ = ["NAME", "SUFFIXES", "WEIGHT_SUM_TOLERANCE", "DQS", "sniff", "UsdSkelScene",
           "AllFramesSkinning", "SkeletonSampler", "read", "IMPLICIT_SEGMENTS", "implicit_surface",
           "bind_transforms"]

NAME = "usdskel"
SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

WEIGHT_SUM_TOLERANCE = 1e-3
"""Weights whose sum differs from 1 by more than this are reported (UsdSkel uses them as they are)."""

DQS = "dualQuaternion"

def sniff(path) -> bool:
    """Whether ``path`` starts like a USD file (text ``#usda``, crate ``PXR-USDC``, or a usdz zip)."""
    with open(path, "rb") as handle:
        head = handle.read(64)
    if head.startswith(b"#usda") or head.startswith(b"PXR-USDC"):
        return True
    return head.startswith(b"PK\x03\x04") and b".usd" in head


@dataclass(frozen=True)
class UsdSkelScene(SourceScene):
    """A :class:`SourceScene` that also answers with UsdSkel's own skinning, for error reports.

    Attributes:
        reference: ``reference(animation_index, mesh_index, times) -> (points, normals)``: UsdSkel's
            skinned points ``(n, V, 3)`` (SkinningQuery.ComputeSkinnedPoints) and normals (or None;
            UsdSkel.SkinNormalsLBS), both in world space, at source times in seconds.
        skinning_methods: Per animation, per mesh, UsdSkel's skinning method token.
    """

    reference: Optional[Callable] = None
    skinning_methods: tuple = ()
    reference_name: str = "UsdSkel.SkinningQuery.ComputeSkinnedPoints"


# --------------------------------------------------------------------------------------------
# Small helpers
# --------------------------------------------------------------------------------------------


def _matrix(value) -> np.ndarray:
    """Gf.Matrix4d -> float64 (4, 4) in USD's row-vector layout."""
    return np.array(value, dtype=np.float64).reshape(4, 4)


def _finite(array) -> bool:
    """Whether every value of a USD array (Vt array, Gf matrix, list) is finite."""
    return all_finite(np.asarray(array, dtype=np.float64))


class _Reader:
    """State of one read: the stage, its file name and collected warnings."""

    def __init__(self, path: Path, options: ReadOptions) -> None:
        self.Usd, self.UsdGeom, self.UsdSkel = Usd, UsdGeom, UsdSkel
        self.path = path
        self.file = str(path)
        self.options = options
        self.warnings: list[str] = []
        self.stage = self._open()
        self.tcps = float(self.stage.GetTimeCodesPerSecond())
        if not math.isfinite(self.tcps) or self.tcps <= 0:
            raise InputError(f"timeCodesPerSecond must be positive, got {self.tcps}", file=self.file,
                             location="/", code="usdskel.timeCodesPerSecond")
        self.cache = UsdSkel.Cache()
        self.predicate = Usd.TraverseInstanceProxies()
        self.bindings: dict = {}
        """Per SkelRoot path: {skinning target path: (skeleton path, UsdSkel.SkinningQuery)}."""
        self.animation_values: dict = {}
        """Per SkelAnimation path: {attribute name: (time codes (n,) float64 in order, or None for
        a value without time samples; values (n, joints, components) as USD stores them)}, what
        :meth:`check_animation` read, reused by :class:`AllFramesSkinning`."""

    def error(self, message: str, location: str, code: str) -> InputError:
        return InputError(message, file=self.file, location=location, code=code)

    def warn(self, location: str, message: str) -> None:
        self.warnings.append(f"{location}: {message}")

    # ---------------------------------------------------------------------------------------
    def _open(self):
        """The stage, opened by vbusd's one USD reader: the same checks, codes and messages as
        every other command (file kind, sniffed content, layers outside the folder, pipes,
        composition errors), USD's own diagnostics captured instead of printed."""

        diagnostics = Diagnostics(self.file, strict=True)
        stage = open_stage(self.path, diagnostics, allow_outside_paths=self.options.allow_outside_paths)
        for finding in diagnostics.findings:  # warnings the strict list did not raise
            self.warn(str(finding.location), f"{finding.code}: {finding.message}")
        return stage

    # ---------------------------------------------------------------------------------------
    def check_binding_api(self) -> None:
        """skel:* properties on a prim without SkelBindingAPI are ignored by UsdSkel: refuse them."""
        binding_properties = ("skel:skeleton", "skel:animationSource", "skel:joints", "skel:blendShapes",
                              "skel:blendShapeTargets", "primvars:skel:jointIndices",
                              "primvars:skel:jointWeights", "primvars:skel:geomBindTransform",
                              "primvars:skel:skinningMethod")
        for prim in self.stage.Traverse(self.predicate):
            if prim.IsA(self.UsdSkel.Animation):
                continue  # SkelAnimation owns its own (non-binding) properties
            authored = [p.GetName() for p in prim.GetAuthoredProperties() if p.GetName() in binding_properties]
            if authored and not prim.HasAPI(self.UsdSkel.BindingAPI):
                raise self.error(f"has {authored[0]} but SkelBindingAPI is not applied (UsdSkel ignores "
                                 "skel:* properties without it; add prepend apiSchemas = [\"SkelBindingAPI\"])",
                                 str(prim.GetPath()), "usdskel.bindingAPI")

    # ---------------------------------------------------------------------------------------
    def skinnable_prims(self) -> list:
        """Prims with authored joint influences, with the skeleton each is bound to.

        Returns:
            ``[(prim, skeleton_prim)]`` in stage order.
        """
        found = []
        for prim in self.stage.Traverse(self.predicate):
            if not prim.HasAPI(self.UsdSkel.BindingAPI):
                continue
            binding = self.UsdSkel.BindingAPI(prim)
            indices = binding.GetJointIndicesPrimvar()
            weights = binding.GetJointWeightsPrimvar()
            has_indices = bool(indices) and indices.HasAuthoredValue()
            has_weights = bool(weights) and weights.HasAuthoredValue()
            if not (has_indices or has_weights):
                shapes = binding.GetBlendShapesAttr()
                if shapes and shapes.HasAuthoredValue() and shapes.Get():
                    found.append((prim, self._bound_skeleton(prim, binding)))
                continue
            location = str(prim.GetPath())
            if has_indices != has_weights:
                missing = "primvars:skel:jointWeights" if has_indices else "primvars:skel:jointIndices"
                raise self.error(f"joint influences need both jointIndices and jointWeights; {missing} is "
                                 "missing", location, "usdskel.influences.missing")
            if self._skel_root(prim) is None:
                self.warn(location, "has joint influences but no SkelRoot above it; UsdSkel does not skin "
                          "it, so it is not converted")
                continue
            found.append((prim, self._bound_skeleton(prim, binding)))
        return found + self.inherited_targets({str(p.GetPath()) for p, _ in found})

    def inherited_targets(self, known: set) -> list:
        """UsdSkel's skinning targets whose joint influences are inherited from an ancestor.

        Constant-interpolation ``jointIndices``/``jointWeights`` (a rigid binding) authored on an
        Xform apply to every gprim below it, as primvars do; UsdSkel rigidly deforms those gprims
        (spec: usd-conversion.md, Rigid bindings). They are found through UsdSkel's own bindings.

        Args:
            known: Paths already found with influences of their own.

        Returns:
            ``[(prim, skeleton_prim)]`` in stage order.
        """
        result = []
        for prim in self.stage.Traverse(self.predicate):
            if not prim.IsA(self.UsdSkel.Root):
                continue
            for entry in self.targets_of_root(prim).items():
                path, (skel_path, _query) = entry
                if path in known:
                    continue
                target = self.stage.GetPrimAtPath(path)
                if self.influence_source(target) is None or not target.IsA(self.UsdGeom.Gprim):
                    continue
                result.append((target, self.stage.GetPrimAtPath(skel_path)))
                known.add(path)
        return result

    def targets_of_root(self, root) -> dict:
        """{skinning target path: (skeleton path, UsdSkel.SkinningQuery)} of one SkelRoot (memoized)."""
        root_key = str(root.GetPath())
        if root_key not in self.bindings:
            skel_root = self.UsdSkel.Root(root)
            self.cache.Populate(skel_root, self.predicate)
            table = {}
            for binding in self.cache.ComputeSkelBindings(skel_root, self.predicate):
                for target in binding.GetSkinningTargets():
                    table[str(target.GetPrim().GetPath())] = (str(binding.GetSkeleton().GetPath()), target)
            self.bindings[root_key] = table
        return self.bindings[root_key]

    def influence_source(self, prim):
        """The prim whose ``primvars:skel:jointIndices`` apply to ``prim``: itself when authored there,
        else the nearest ancestor with constant-interpolation influences (inherited, as primvars are);
        None when there is none."""
        node = prim
        while node and not node.IsPseudoRoot():
            primvar = self.UsdSkel.BindingAPI(node).GetJointIndicesPrimvar()
            if primvar and primvar.HasAuthoredValue():
                if node == prim or primvar.GetInterpolation() == "constant":
                    return node
                return None
            node = node.GetParent()
        return None

    def _skel_root(self, prim):
        parent = prim
        while parent and not parent.IsPseudoRoot():
            if parent.IsA(self.UsdSkel.Root):
                return parent
            parent = parent.GetParent()
        return None

    def _bound_skeleton(self, prim, binding):
        location = str(prim.GetPath())
        # Find the nearest authored skel:skeleton ourselves (UsdSkel warns on a dangling target and
        # returns nothing), to say whether it is missing or dangling.
        node = prim
        while node and not node.IsPseudoRoot():
            rel = node.GetRelationship("skel:skeleton")
            if rel and rel.HasAuthoredTargets():
                targets = rel.GetForwardedTargets()
                if not targets:
                    break
                target = self.stage.GetPrimAtPath(targets[0])
                if target and target.IsValid() and target.IsA(self.UsdSkel.Skeleton):
                    return target
                what = ("does not exist" if not target or not target.IsValid()
                        else f"is a {target.GetTypeName() or 'typeless prim'}, not a Skeleton")
                raise self.error(f"skel:skeleton (on {node.GetPath()}) targets {targets[0]}, which {what}",
                                 location, "usdskel.skeleton.dangling")
            node = node.GetParent()
        raise self.error("has joint influences but no skel:skeleton binding (on it or an ancestor)",
                         location, "usdskel.skeleton.missing")

    # ---------------------------------------------------------------------------------------
    def check_joint_counts(self) -> None:
        """Every Skeleton's joint count within what a texture row holds, before UsdSkel builds a
        topology for it (a million joints would take it seconds and gigabytes first)."""

        most = MAX_TEXTURE_DIMENSION // min(e.texels_per_bone for e in Encoding)
        for prim in self.stage.Traverse(self.predicate):
            if not prim.IsA(self.UsdSkel.Skeleton):
                continue
            joints = self.UsdSkel.Skeleton(prim).GetJointsAttr().Get()
            if joints is not None and len(joints) > most:
                raise self.error(f"the skeleton has {len(joints)} joints; a Virtual Bones texture holds at most "
                                 f"{most} bones ({MAX_TEXTURE_DIMENSION} texels per row)",
                                 f"{prim.GetPath()}.joints", "layout.size")

    def check_skeleton(self, skel_prim) -> tuple:
        """Check a Skeleton's joints, bind and rest transforms. Returns its joint tokens."""
        location = str(skel_prim.GetPath())
        skeleton = self.UsdSkel.Skeleton(skel_prim)
        joints = list(skeleton.GetJointsAttr().Get() or [])
        seen = {}
        for i, joint in enumerate(joints):
            if joint in seen:
                raise self.error(f"joint '{joint}' appears twice in joints (indices {seen[joint]} and {i})",
                                 f"{location}.joints", "usdskel.joints.duplicate")
            seen[joint] = i

        for i, joint in enumerate(joints):
            if not Sdf.Path.IsValidPathString(str(joint)):
                raise self.error(f"joint {i} '{joint}' is not a valid path", f"{location}.joints",
                                 "usdskel.joints.invalid")
            parent = str(Sdf.Path(str(joint)).GetParentPath())
            if parent in seen and seen[parent] > i:
                raise self.error(f"joint '{joint}' (index {i}) comes before its parent '{parent}' (index "
                                 f"{seen[parent]}); joints must be ordered parent first",
                                 f"{location}.joints", "usdskel.joints.order")
        for name, attr in (("bindTransforms", skeleton.GetBindTransformsAttr()),
                           ("restTransforms", skeleton.GetRestTransformsAttr())):
            if not attr or not attr.HasAuthoredValue():
                if name == "bindTransforms" and joints:
                    raise self.error("bindTransforms is missing", f"{location}.{name}",
                                     "usdskel.bindTransforms.missing")
                continue
            value = attr.Get()
            count = 0 if value is None else len(value)
            if count != len(joints):
                raise self.error(f"{name} has {count} matrices for {len(joints)} joints",
                                 f"{location}.{name}", f"usdskel.{name}.count")
            array = np.array(value, dtype=np.float64).reshape(-1, 4, 4)
            if not _finite(array):
                bad = int(np.argwhere(~np.isfinite(array))[0][0])
                raise self.error(f"{name}[{bad}] (joint '{joints[bad]}') is not finite",
                                 f"{location}.{name}", "usdskel.transform.nonFinite")
            if name == "bindTransforms":
                dets = np.linalg.det(array[:, :3, :3])
                if np.any(np.abs(dets) < 1e-12):
                    bad = int(np.argmax(np.abs(dets) < 1e-12))
                    raise self.error(f"bindTransforms[{bad}] (joint '{joints[bad]}') is singular",
                                     f"{location}.{name}", "usdskel.bindTransforms.singular")
        return tuple(str(j) for j in joints)

    def check_animation(self, anim_prim, skel_joints: tuple) -> None:
        """Check a SkelAnimation: joints, array lengths at every sample, finite values."""
        location = str(anim_prim.GetPath())
        anim = self.UsdSkel.Animation(anim_prim)
        joints = [str(j) for j in (anim.GetJointsAttr().Get() or [])]
        seen = set()
        for joint in joints:
            if joint in seen:
                raise self.error(f"joint '{joint}' appears twice in joints", f"{location}.joints",
                                 "usdskel.joints.duplicate")
            seen.add(joint)
        unknown = [j for j in joints if j not in set(skel_joints)]
        if unknown:
            self.warn(location, f"{len(unknown)} animated joint(s) are not joints of the skeleton and are "
                      f"ignored (first: '{unknown[0]}')")
        attrs = {"translations": anim.GetTranslationsAttr(), "rotations": anim.GetRotationsAttr(),
                 "scales": anim.GetScalesAttr()}
        authored = {name: a for name, a in attrs.items() if a and a.HasAuthoredValue()}
        if joints and authored and len(authored) < 3:
            missing = sorted(set(attrs) - set(authored))
            raise self.error(f"{', '.join(missing)} missing: UsdSkel ignores an animation without all of "
                             "translations, rotations and scales", location, "usdskel.animation.incomplete")
        stash = self.animation_values.setdefault(location, {})
        for name, attr in authored.items():
            times = list(attr.GetTimeSamples())
            if times:  # a query resolves where the value comes from once, not per sample
                query = self.Usd.AttributeQuery(attr)
                kept = [query.Get(time) for time in times]
            else:
                kept = [attr.Get()]
            # once, for the checks and for AllFramesSkinning
            kept = [None if value is None else np.asarray(value) for value in kept]
            for index, value in enumerate(kept):
                count = 0 if value is None else len(value)
                if count != len(joints):
                    where = f"{location}.{name}" + (f" at time {times[index]:g}" if times else "")
                    raise self.error(f"{name} has {count} values for {len(joints)} joints", where,
                                     "usdskel.animation.count")
            if joints:  # every sample at once: (samples, joints, components)
                stacked = np.stack(kept).reshape(len(kept), len(joints), -1)
                self._check_values(name, stacked, times, location, joints)
                stash[name] = (np.asarray(times, dtype=np.float64) if times else None, stacked)

    def _check_values(self, name: str, stacked: np.ndarray, times: list, location: str, joints: list) -> None:
        """Finite values, and no zero quaternion, in every sample of one animation attribute; the
        first bad value (earliest time, then lowest joint) is the one reported."""
        bad = None if all_finite(stacked) else ~np.isfinite(stacked).all(axis=2)
        problem, code = "is not finite", "usdskel.animation.nonFinite"
        if (bad is None or not bad.any()) and name == "rotations":
            wide = stacked.astype(np.float32, copy=False)  # half's squares would underflow
            bad = np.sqrt(np.einsum("sjc,sjc->sj", wide, wide)) < 1e-6
            problem, code = "is a zero quaternion", "usdskel.animation.zeroQuaternion"
        if bad is None or not bad.any():
            return
        sample, joint = (int(i) for i in np.argwhere(bad)[0])
        where = f"{location}.{name}" + (f" at time {times[sample]:g}" if times else "")
        raise self.error(f"{name}[{joint}] (joint '{joints[joint]}') {problem}", where, code)


# --------------------------------------------------------------------------------------------
# Influences and meshes
# --------------------------------------------------------------------------------------------


def _read_influences(reader: _Reader, prim, point_count: int, joint_count: int):
    """Return (indices (V, K) into the binding's joint list, weights (V, K), interpolation)."""
    location = str(prim.GetPath())
    binding = reader.UsdSkel.BindingAPI(prim)
    ind_pv, wgt_pv = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    interps = (ind_pv.GetInterpolation(), wgt_pv.GetInterpolation())
    if interps[0] != interps[1]:
        raise reader.error(f"jointIndices interpolation '{interps[0]}' differs from jointWeights "
                           f"interpolation '{interps[1]}'", location, "usdskel.influences.interpolation")
    if interps[0] not in ("vertex", "constant"):
        raise reader.error(f"joint influences have interpolation '{interps[0]}'; UsdSkel allows only "
                           "'vertex' or 'constant'", location, "usdskel.influences.interpolation")
    sizes = (ind_pv.GetElementSize(), wgt_pv.GetElementSize())
    if sizes[0] != sizes[1]:
        raise reader.error(f"jointIndices elementSize {sizes[0]} differs from jointWeights elementSize "
                           f"{sizes[1]}", location, "usdskel.influences.elementSize")
    k = int(sizes[0])
    if k < 1:
        raise reader.error(f"joint influences have elementSize {k}; it must be at least 1", location,
                           "usdskel.influences.elementSize")
    indices = np.asarray(ind_pv.Get() or [], dtype=np.int64)
    weights = np.asarray(wgt_pv.Get() or [], dtype=np.float64)
    expected = k if interps[0] == "constant" else k * point_count
    for name, array in (("jointIndices", indices), ("jointWeights", weights)):
        if array.size != expected:
            what = f"{k} (constant, elementSize {k})" if interps[0] == "constant" else \
                f"{expected} ({point_count} points x elementSize {k})"
            raise reader.error(f"{name} has {array.size} values, expected {what}", location,
                               "usdskel.influences.count")
    indices, weights = indices.reshape(-1, k), weights.reshape(-1, k)
    if indices.size and (indices.min() < 0 or indices.max() >= joint_count):
        bad_flat = int(np.argmax((indices < 0) | (indices >= joint_count)))
        point, value = bad_flat // k, int(indices.reshape(-1)[bad_flat])
        raise reader.error(f"jointIndices value {value} (point {point}) is out of range 0..{joint_count - 1}",
                           location, "usdskel.influences.range")
    if not np.all(np.isfinite(weights)):
        point = int(np.argwhere(~np.isfinite(weights))[0][0])
        raise reader.error(f"jointWeights of point {point} are not finite", location,
                           "usdskel.influences.nonFinite")
    if np.any(weights < 0):
        point = int(np.argwhere(weights < 0)[0][0])
        raise reader.error(f"jointWeights of point {point} has a negative weight {weights[point].min():g}",
                           location, "usdskel.influences.negative")
    totals = weights.sum(axis=1)
    if np.any(totals <= 0):
        point = int(np.argmax(totals <= 0))
        raise reader.error(f"jointWeights of point {point} are all zero", location,
                           "usdskel.influences.zero")
    off = np.abs(totals - 1.0) > WEIGHT_SUM_TOLERANCE
    if np.any(off):
        reader.warn(location, f"weights of {int(off.sum())} point(s) do not sum to 1 (e.g. point "
                    f"{int(np.argmax(off))}: {totals[np.argmax(off)]:g}); UsdSkel uses them as they are, "
                    "vbusd normalizes them (the error report shows the difference)")
    if interps[0] == "constant":
        indices = np.repeat(indices, point_count, axis=0)
        weights = np.repeat(weights, point_count, axis=0)
    return indices, weights, interps[0]


def _joint_map(reader: _Reader, prim, skel_joints: tuple) -> np.ndarray:
    """Indices into the skeleton's joints of the binding's joint list (mesh-local skel:joints)."""
    location = str(prim.GetPath())
    attr = reader.UsdSkel.BindingAPI(prim).GetJointsAttr()
    if not attr or not attr.HasAuthoredValue():
        return np.arange(len(skel_joints))
    local = [str(j) for j in (attr.Get() or [])]
    position = {j: i for i, j in enumerate(skel_joints)}
    seen = set()
    result = []
    for joint in local:
        if joint in seen:
            raise reader.error(f"skel:joints lists '{joint}' twice", f"{location}.skel:joints",
                               "usdskel.joints.duplicate")
        seen.add(joint)
        if joint not in position:
            raise reader.error(f"skel:joints names '{joint}', which is not a joint of the skeleton",
                               f"{location}.skel:joints", "usdskel.joints.unknown")
        result.append(position[joint])
    return np.asarray(result, dtype=np.int64)


def _normals(reader: _Reader, mesh, counts: np.ndarray, fvi: np.ndarray, point_count: int, time):
    """Rest normals and their interpolation (vertex or faceVarying), or (None, 'vertex')."""
    location = str(mesh.GetPath())
    primvar = reader.UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("normals")
    if primvar and primvar.HasAuthoredValue():
        values, interp = primvar.ComputeFlattened(time), primvar.GetInterpolation()
    else:
        attr = mesh.GetNormalsAttr()
        if not attr or not attr.HasAuthoredValue():
            return None, "vertex"
        values, interp = attr.Get(time), mesh.GetNormalsInterpolation()
    normals = np.asarray(values if values is not None else [], dtype=np.float64).reshape(-1, 3)
    if normals.size == 0:
        return None, "vertex"
    if interp in ("vertex", "varying"):
        expected, interp = point_count, "vertex"
    elif interp == "faceVarying":
        expected = fvi.size
    elif interp == "uniform":
        expected = counts.size
    else:  # constant
        expected = 1
    if normals.shape[0] != expected:
        reader.warn(location, f"{normals.shape[0]} normals for {interp} interpolation (expected {expected}); "
                    "normals are not converted")
        return None, "vertex"
    if not _finite(normals):
        raise reader.error("normals are not finite", f"{location}.normals", "usdskel.normals.nonFinite")
    if interp == "uniform":
        normals, interp = np.repeat(normals, counts, axis=0), "faceVarying"
    elif interp == "constant":
        normals, interp = np.repeat(normals, fvi.size, axis=0), "faceVarying"
    return normals, interp


# --------------------------------------------------------------------------------------------
# Sampling the skeleton through UsdSkel
# --------------------------------------------------------------------------------------------


def _quaternion_matrices(quats: np.ndarray, axis: int = -1) -> np.ndarray:
    """Row-vector rotation matrices of quaternions stored as (i, j, k, real) along ``axis``, as Gf does it.

    ``GfMatrix3f(GfQuatf)``'s formula in float32, without normalizing (a non-unit quaternion
    scales, in UsdSkel too), so the result equals UsdSkel's bit for bit before the cast to double.
    The 3 x 3 matrix takes the place of ``axis`` (``(..., 4)`` -> ``(..., 3, 3)``; with ``axis=1``,
    ``(A, 4, n)`` -> ``(A, 3, 3, n)``).
    """
    q = np.moveaxis(np.asarray(quats, dtype=np.float32), axis, 0)
    x, y, z, w = q[0], q[1], q[2], q[3]
    one, two = np.float32(1.0), np.float32(2.0)
    m = np.empty((3, 3) + x.shape, dtype=np.float32)
    m[0, 0] = one - two * (y * y + z * z)
    m[0, 1] = two * (x * y + z * w)
    m[0, 2] = two * (z * x - y * w)
    m[1, 0] = two * (x * y - z * w)
    m[1, 1] = one - two * (z * z + x * x)
    m[1, 2] = two * (y * z + x * w)
    m[2, 0] = two * (z * x + y * w)
    m[2, 1] = two * (y * z - x * w)
    m[2, 2] = one - two * (y * y + x * x)
    axis = axis % np.asarray(quats).ndim
    return np.moveaxis(m, (0, 1), (axis, axis + 1))


def _affine_rows(matrices: np.ndarray) -> bool:
    """Whether row-vector matrices (..., 4, 4) are affine (last column 0, 0, 0, 1 within 1e-12), as
    skeletons' are (exporters leave 0.9999999999999998 in the corner: the difference is rounding)."""
    return bool(np.all(np.abs(matrices[..., :3, 3]) <= 1e-12) and np.all(np.abs(matrices[..., 3, 3] - 1.0) <= 1e-12))


def _at_authored_codes(read: Optional[tuple], codes: np.ndarray) -> Optional[np.ndarray]:
    """The values a reader read, ``(time codes or None, (n, ...) values)``, at ``codes``; None when
    nothing was read or some code falls between authored time codes."""
    if read is None:
        return None
    times, values = read
    if times is None:  # one value, no time samples: the same at every code
        return np.broadcast_to(values[0], (codes.size,) + values.shape[1:])
    # The nearest authored code, taken when within the 1e-9 the sampler's codes are rounded to.
    right = np.clip(np.searchsorted(times, codes), 0, times.size - 1)
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(times[left] - codes) < np.abs(times[right] - codes), left, right)
    return values[nearest] if np.all(np.abs(times[nearest] - codes) <= 5e-10) else None


def _in_code_order(out: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """Results per distinct sorted code (``np.unique``) back in the order and repeats of the codes."""
    inverse = inverse.reshape(-1)
    return out if np.array_equal(inverse, np.arange(out.shape[0])) else out[inverse]


class AllFramesSkinning:
    """UsdSkel's skinning transforms of one skeleton at many time codes at once.

    ``SkeletonQuery.ComputeSkinningTransforms`` evaluates one time code per call (its joint local
    transforms, the remap from the animation's joint order, the concatenation down the hierarchy
    and the inverse bind transforms). This class takes the animation's translations, rotations and
    scales at every time code (the samples the reader's checks already read when the codes are the
    authored ones; else ``Usd.AttributeQuery.Get``: USD's own interpolation between samples, slerp
    for quaternions) and does the same arithmetic for all frames together, in numpy, or for many
    frames in its compiled twin (:func:`vbusd.kernels.bake.skinning_transforms`):

    * local ``L = S * R(q) * T`` (row-vector), with ``R(q)`` and the scale product in float32 as
      ``UsdSkelMakeTransform`` computes them, then in float64;
    * joints missing from the animation keep their rest transform (UsdSkel's sparse remap);
    * ``skel[j] = L[j] * skel[parent(j)]``, joints in topological order (one batched product per depth);
    * skinning ``= inverse(bind[j]) * skel[j]``.

    ``compute`` returns None whenever UsdSkel could treat a frame specially (a value missing or of
    the wrong length at some time code); the sampler then asks UsdSkel frame by frame. Both paths
    are checked against ``ComputeSkinningTransforms`` on every shared asset
    (tests/test_usdskel_all_frames.py).
    """

    def __init__(self, usd, parents: np.ndarray, inverse_bind: np.ndarray, rest: Optional[np.ndarray],
                 queries: Optional[tuple], anim_to_skel: Optional[np.ndarray], anim_joint_count: int) -> None:
        self._usd = usd
        self._parents = parents
        self._inverse_bind = inverse_bind
        self._rest = rest
        self._queries = queries
        self._anim_to_skel = anim_to_skel
        self._anim_joint_count = anim_joint_count
        self._read: tuple = (None, None, None)
        """Values the reader's checks read (translations, rotations, scales): ``(time codes or None,
        (n, A, components) values)`` each, or None."""
        depth = np.zeros(parents.size, dtype=np.int64)
        for joint, parent in enumerate(parents):
            depth[joint] = depth[parent] + 1 if parent >= 0 else 0
        self._levels = [(np.flatnonzero(depth == d), parents[depth == d]) for d in range(1, int(depth.max(initial=0)) + 1)]

    @classmethod
    def build(cls, reader, skel_query) -> Optional["AllFramesSkinning"]:
        """Set up for one skeleton, or None when its animation is not a plain ``UsdSkel.Animation``."""
        Usd, UsdSkel = reader.Usd, reader.UsdSkel
        try:
            parents = np.asarray(skel_query.GetTopology().GetParentIndices(), dtype=np.int64)
            joint_count = len(skel_query.GetJointOrder())
            bind = np.asarray(skel_query.GetJointWorldBindTransforms(), dtype=np.float64).reshape(-1, 4, 4)
            if joint_count == 0 or parents.shape != (joint_count,) or bind.shape[0] != joint_count:
                return None
            if np.any(parents >= np.arange(joint_count)):  # UsdSkel orders parents first; else ask it
                return None
            if not _affine_rows(bind):
                return None
            inverse_bind = np.linalg.inv(bind)
            inverse_bind[:, :3, 3], inverse_bind[:, 3, 3] = 0.0, 1.0  # exact, as the bind's are
            rest = None
            if skel_query.HasRestPose():
                rest = np.asarray(skel_query.ComputeJointLocalTransforms(Usd.TimeCode.Default(), True),
                                  dtype=np.float64).reshape(-1, 4, 4)
                if rest.shape[0] != joint_count or not _affine_rows(rest):
                    return None
            anim_query = skel_query.GetAnimQuery()
            if not anim_query:
                if rest is None:
                    return None
                return cls(Usd, parents, inverse_bind, rest, None, None, 0)
            prim = anim_query.GetPrim()
            if not prim.IsA(UsdSkel.Animation):
                return None
            anim = UsdSkel.Animation(prim)
            anim_joints = [str(j) for j in anim_query.GetJointOrder()]
            skel_index = {str(j): i for i, j in enumerate(skel_query.GetJointOrder())}
            if len(set(anim_joints)) != len(anim_joints):
                return None
            anim_to_skel = np.array([skel_index.get(j, -1) for j in anim_joints], dtype=np.int64)
            covered = np.zeros(joint_count, dtype=bool)
            covered[anim_to_skel[anim_to_skel >= 0]] = True
            if not covered.all() and rest is None:
                return None
            queries = tuple(Usd.AttributeQuery(attr) for attr in
                            (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr()))
            fast = cls(Usd, parents, inverse_bind, rest, queries, anim_to_skel, len(anim_joints))
            read = getattr(reader, "animation_values", {}).get(str(prim.GetPath())) or {}
            fast._read = tuple(read.get(name) for name in ("translations", "rotations", "scales"))
            return fast
        except Exception:  # noqa: BLE001 - any surprise: UsdSkel frame by frame stays the answer
            return None

    def _animation_values(self, codes: np.ndarray) -> Optional[tuple]:
        """The animation's ``(translations (n, A, 3) float32, rotations (n, A, 4) float32, scales
        (n, A, 3) float16)`` at ``codes``; None when a value is missing or of the wrong length."""
        frames, count = codes.size, self._anim_joint_count
        gathered = [_at_authored_codes(read, codes) for read in self._read]
        if any(g is None for g in gathered):  # some code between samples: USD interpolates
            gathered = self._animation_values_from_usd(codes)
            if gathered is None:
                return None
        try:
            translations = np.asarray(gathered[0]).astype(np.float32, copy=False)
            rotations = np.asarray(gathered[1]).astype(np.float32, copy=False)
            scales = np.asarray(gathered[2]).astype(np.float16, copy=False)
        except ValueError:  # arrays of different lengths at different times
            return None
        if translations.shape != (frames, count, 3) or rotations.shape != (frames, count, 4) \
                or scales.shape != (frames, count, 3):
            return None
        return translations, rotations, scales

    def _animation_values_from_usd(self, codes: np.ndarray) -> Optional[list]:
        """Values at every code through ``Usd.AttributeQuery.Get`` (USD's interpolation), or None."""
        TimeCode = self._usd.TimeCode
        columns: list = [[], [], []]
        for code in codes.tolist():
            values = tuple(query.Get(TimeCode(code)) for query in self._queries)
            if any(v is None for v in values):
                return None
            for column, value in zip(columns, values):
                column.append(np.asarray(value))
        try:
            return [np.stack(column) for column in columns]
        except ValueError:
            return None

    def _local(self, codes: np.ndarray, animated: Optional[tuple]) -> tuple:
        """Joint local transforms at ``codes`` as (linear (J, 3, 3, n), translation (J, 3, n)), frames
        last, from :meth:`_animation_values` (None: no animation, every joint at rest)."""
        joint_count, frames = self._parents.size, codes.size
        if self._rest is not None:
            linear = np.repeat(self._rest[:, :3, :3, None], frames, axis=-1)
            translation = np.repeat(self._rest[:, 3, :3, None], frames, axis=-1)
        else:
            linear = np.empty((joint_count, 3, 3, frames))
            translation = np.empty((joint_count, 3, frames))
        if animated is None:
            return linear, translation
        translations, rotations, scales = animated
        rotation = _quaternion_matrices(np.moveaxis(rotations, 0, -1), axis=1)  # (A, 3, 3, n) float32
        anim_linear = rotation * np.moveaxis(scales, 0, -1).astype(np.float32)[:, :, None, :]
        used = self._anim_to_skel >= 0
        targets = self._anim_to_skel[used]
        linear[targets] = anim_linear[used]
        translation[targets] = np.moveaxis(translations, 0, -1)[used]
        return linear, translation

    def compute(self, codes, world: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
        """World-space skinning matrices ``(len(codes), joints, 4, 4)``, column-vector, or None.

        Args:
            codes: USD time codes (already clamped to the clip).
            world: The skeleton's row-vector local-to-world matrix (4, 4), the same at every code,
                or ``(len(codes), 4, 4)``; None for skeleton space.

        Returns:
            ``(S_j(t) * W(t))^T`` per code and joint, as :class:`SkeletonSampler` returns them;
            None when UsdSkel must answer frame by frame.
        """
        codes = np.atleast_1d(np.asarray(codes, dtype=np.float64))
        joint_count = self._parents.size
        if world is not None and not _affine_rows(np.asarray(world)):
            return None
        if codes.size == 0:
            return np.zeros((0, joint_count, 4, 4))
        if world is not None and np.asarray(world).ndim == 3:
            unique, inverse = codes, np.arange(codes.size)  # a moving skeleton: every code as given
        else:
            unique, inverse = np.unique(codes, return_inverse=True)
        animated = None if self._queries is None else self._animation_values(unique)
        if self._queries is not None and animated is None:
            return None
        if animated is not None and (world is None or np.asarray(world).ndim == 2):

            anim_joint = np.full(joint_count, -1, dtype=np.int64)
            used = self._anim_to_skel >= 0
            anim_joint[self._anim_to_skel[used]] = np.flatnonzero(used)
            out = bake_kernels.skinning_transforms(*animated, anim_joint, self._rest, self._parents,
                                                   self._inverse_bind, world)
            if out is not None:  # the same products, compiled, frame by frame
                return _in_code_order(out, inverse)
        local = self._local(unique, animated)
        # Affine row-vector matrices [[A, 0], [t, 1]]: (A1, t1) * (A2, t2) = (A1 A2, t1 A2 + t2);
        # arrays hold frames last, so every product is a few multiply-adds over contiguous frames.
        linear, translation = local
        for joints, parents in self._levels:  # concatenated in place, one depth at a time
            parent_linear = linear[parents]
            translation[joints] = np.einsum("kbn,kbcn->kcn", translation[joints], parent_linear) + translation[parents]
            linear[joints] = np.einsum("kabn,kbcn->kacn", linear[joints], parent_linear)
        # Skinning transforms inverse(bind) * skel, then the skeleton's placement in the world.
        translation = np.einsum("jb,jbcn->jcn", self._inverse_bind[:, 3, :3], linear) + translation
        linear = np.einsum("jab,jbcn->jacn", self._inverse_bind[:, :3, :3], linear)
        if world is not None:
            world = np.asarray(world, dtype=np.float64)
            if world.ndim == 2:
                translation = np.einsum("jbn,bc->jcn", translation, world[:3, :3]) + world[3, :3, None]
                linear = np.einsum("jabn,bc->jacn", linear, world[:3, :3])
            else:  # (n, 4, 4): a skeleton that moves
                rotation = np.moveaxis(world[:, :3, :3], 0, -1)
                translation = np.einsum("jbn,bcn->jcn", translation, rotation) + world[:, 3, :3].T
                linear = np.einsum("jabn,bcn->jacn", linear, rotation)
        out = np.zeros((unique.size, joint_count, 4, 4))
        out[..., :3, :3] = linear.transpose(3, 0, 2, 1)  # column-vector: the transpose
        out[..., :3, 3] = translation.transpose(2, 0, 1)
        out[..., 3, 3] = 1.0
        return _in_code_order(out, inverse)


class SkeletonSampler:
    """World-space skinning matrices of one skeleton at any time, evaluated by UsdSkel.

    ``sample(times)`` returns ``(len(times), joints, 4, 4)`` column-vector matrices, all times at
    once through :class:`AllFramesSkinning`; where it cannot answer, each distinct time code is
    evaluated by UsdSkel.SkeletonQuery.ComputeSkinningTransforms (which interpolates between
    authored samples as UsdSkel does) and cached. The error report always asks UsdSkel itself
    (:meth:`usd_transforms`). Times outside [start, end] hold the first or last pose.
    """

    def __init__(self, reader: _Reader, skel_query, skel_prim, start_code: float, end_code: float) -> None:
        self._query = skel_query
        self._xformable = reader.UsdGeom.Xformable(skel_prim)
        self._cache_xf = reader.UsdGeom.XformCache()
        self._usd = reader.Usd
        self._tcps = reader.tcps
        self._start, self._end = float(start_code), float(end_code)
        self._location = str(skel_prim.GetPath())
        self._file = reader.file
        self._joints = len(skel_query.GetJointOrder())
        self._static_world = None
        if not self._world_might_vary(skel_prim, reader):
            self._static_world = self._world(self._start)
        self._memo: dict = {}
        self.on_progress: Optional[Callable] = None
        """``on_progress(done, total)`` while sampling many rows (UsdSkel evaluates them one by one)."""
        self.normal_memo: dict = {}
        """UsdSkel normal matrices per (time code, joint mapping), shared by the error reference."""
        self._all_frames = AllFramesSkinning.build(reader, skel_query)
        """The skinning transforms of many time codes at once (None: UsdSkel, frame by frame)."""
        self.extra_prims: list = []
        """Prims whose own local-to-world transform is an extra bone after the joints (spec:
        usd-conversion.md, Meshes no binding reaches)."""

    def extra_world(self, codes) -> np.ndarray:
        """Row-vector local-to-world transforms ``(len(codes), extra bones, 4, 4)`` of the extra prims."""
        out = np.empty((len(codes), len(self.extra_prims), 4, 4))
        cache = self._usd_xform_cache
        for i, code in enumerate(codes):
            cache.SetTime(self._usd.TimeCode(float(code)))
            for k, prim in enumerate(self.extra_prims):
                out[i, k] = _matrix(cache.GetLocalToWorldTransform(prim))
        if not _finite(out):
            raise InputError("the local-to-world transform of a mesh no binding reaches is not finite",
                             file=self._file, location=str(self.extra_prims[0].GetPath()),
                             code="usdskel.transform.nonFinite")
        return out

    @property
    def _usd_xform_cache(self):
        if not hasattr(self, "_extra_cache"):

            self._extra_cache = UsdGeom.XformCache()
        return self._extra_cache

    def _with_extra(self, matrices: np.ndarray, codes) -> np.ndarray:
        if not self.extra_prims:
            return matrices
        extra = np.transpose(self.extra_world(codes), (0, 1, 3, 2))   # row-vector -> column-vector
        return np.ascontiguousarray(np.concatenate([matrices, extra], axis=1))

    @staticmethod
    def _world_might_vary(prim, reader) -> bool:
        node = prim
        while node and not node.IsPseudoRoot():
            if node.IsA(reader.UsdGeom.Xformable) and reader.UsdGeom.Xformable(node).TransformMightBeTimeVarying():
                return True
            node = node.GetParent()
        return False

    def _world(self, code: float) -> np.ndarray:
        self._cache_xf.SetTime(self._usd.TimeCode(code))
        world = _matrix(self._cache_xf.GetLocalToWorldTransform(self._xformable.GetPrim()))
        if not _finite(world):
            raise InputError(f"the skeleton's local-to-world transform is not finite at time code {code:g}",
                             file=self._file, location=self._location, code="usdskel.transform.nonFinite")
        return world

    @property
    def start_code(self) -> float:
        """The clip's first time code (where the converter reads the rest shape)."""
        return self._start

    def code(self, time: float) -> float:
        """Time code of a source time (seconds), clamped to the clip.

        A code within 1e-9 (relative) of a whole time code is that time code: ``(1/24 + 8098/24) * 24``
        is 8099.000000000001 in floating point, and USD would interpolate the samples there in
        float32 instead of returning the authored sample (a 1e-6 difference on a deep rig).
        """
        return float(self.codes(np.array([float(time)]))[0])

    def codes(self, times: np.ndarray) -> np.ndarray:
        """:meth:`code` of every time in ``times`` (float64 seconds), at once."""
        code = np.asarray(times, dtype=np.float64) * self._tcps
        whole = np.round(code)  # half to even, as Python's round
        code = np.where(np.abs(code - whole) <= 1e-9 * np.maximum(1.0, np.abs(code)), whole, code)
        return np.minimum(np.maximum(code, self._start), self._end)

    def usd_transforms(self, code: float) -> tuple:
        """(UsdSkel's skel-space skinning transforms as a Vt.Matrix4dArray, row-vector world matrix)."""
        key = round(code, 9)
        hit = self._memo.get(key)
        if hit is None:
            transforms = self._query.ComputeSkinningTransforms(self._usd.TimeCode(code))
            if transforms is None or len(transforms) != self._joints:
                raise InputError(f"UsdSkel could not compute skinning transforms at time code {code:g}",
                                 file=self._file, location=self._location, code="usdskel.skinning")
            world = self._static_world if self._static_world is not None else self._world(code)
            hit = self._memo[key] = (transforms, world, None)
        return hit[0], hit[1]

    def at_code(self, code: float) -> np.ndarray:
        """Row-vector skinning matrices (joints, 4, 4) in world space at one time code."""
        transforms, world = self.usd_transforms(code)
        key = round(code, 9)
        cached = self._memo[key][2]
        if cached is None:
            skel = np.array(transforms, dtype=np.float64).reshape(self._joints, 4, 4)
            cached = skel @ world
            self._memo[key] = (transforms, world, cached)
        return cached

    def __call__(self, times) -> np.ndarray:
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        codes = self.codes(times)
        if self._all_frames is not None:
            world = self._static_world
            if world is None:
                world = np.stack([self._world(code) for code in codes])
            matrices = self._all_frames.compute(codes, world)
            if matrices is not None:
                return self._with_extra(matrices, codes)
            self._all_frames = None  # UsdSkel would treat some sample specially: ask it, frame by frame
        out = np.empty((times.size, self._joints, 4, 4))
        report = self.on_progress if times.size >= 512 else None
        for i, code in enumerate(codes):
            out[i] = self.at_code(code)
            if report is not None and (i + 1) % 256 == 0:
                report(i + 1, times.size)
        return self._with_extra(np.ascontiguousarray(np.transpose(out, (0, 1, 3, 2))), codes)  # column-vector


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


@dataclass
class _Bound:
    prim: object
    mesh: SkinnedMesh
    query: object  # UsdSkel.SkinningQuery
    method: str
    joint_map: np.ndarray
    implicit_points: Optional[np.ndarray] = None
    """For a Cube, Sphere, Cylinder, Cone or Capsule: its tessellated points (prim space)."""
    loose: bool = False
    """A gprim no binding reaches, following its own transform (an extra bone)."""


@dataclass
class _SkelWork:
    skel_prim: object
    joints: tuple
    targets: list = field(default_factory=list)
    codes: list = field(default_factory=list)
    """The clip's key time codes (set before the meshes are read)."""
    anim_query: object = None


def _check_options(options: ReadOptions) -> None:
    if not isinstance(options, ReadOptions):
        raise OptionsError(f"options must be ReadOptions, got {type(options).__name__}", file=NAME)
    if options.time_range is not None:
        try:
            start, end = (float(v) for v in options.time_range)
        except (TypeError, ValueError):
            raise OptionsError(f"time_range must be (start, end), got {options.time_range!r}", file=NAME) from None
        if not (math.isfinite(start) and math.isfinite(end)) or end < start:
            raise OptionsError(f"time_range must be finite with start <= end, got {options.time_range!r}",
                               file=NAME)


def _time_samples(reader: _Reader, skel_query, skel_prim) -> list:
    """Union of the time codes at which the animation or the skeleton's placement is authored."""
    codes = set()
    anim = skel_query.GetAnimQuery()
    if anim:
        codes.update(float(t) for t in anim.GetJointTransformTimeSamples())
    node = skel_prim
    while node and not node.IsPseudoRoot():
        if node.IsA(reader.UsdGeom.Xformable):
            codes.update(float(t) for t in reader.UsdGeom.Xformable(node).GetTimeSamples())
        node = node.GetParent()
    return sorted(codes)


def _native_rate(codes: list, tcps: float) -> float:
    """One row per time code, or the key rate when keys are uniform and closer than one time code."""
    if len(codes) >= 3:
        steps = np.diff(np.asarray(codes))
        # 1% jitter: exporters write float32 time codes (BrainStem's 0.9867-code steps vary by 0.4%).
        if steps.min() > 0 and (steps.max() - steps.min()) <= 1e-2 * steps.mean() and steps.mean() < 1.0:
            return tcps / float(steps.mean())
    return tcps


def read(path, options: ReadOptions = ReadOptions()) -> UsdSkelScene:
    """Read every skinned mesh and skeleton animation of a UsdSkel stage.

    USD's own diagnostics while reading are captured and become warnings of the scene
    (``usd.diagnostic``), never raw console lines.

    Args:
        path: A .usd, .usda, .usdc or .usdz file.
        options: Which skeletons (Skeleton prim paths) and which time codes; see
            :class:`vbusd.format.model.ReadOptions`.

    Returns:
        A :class:`UsdSkelScene`: one :class:`SkinnedAnimation` per selected skeleton with meshes,
        stage metadata, warnings, and UsdSkel's own skinning as an error reference.

    Raises:
        OptionsError: Bad options, or a ``--skeleton`` that is not a bound Skeleton of the stage.
        InputError: The stage breaks a UsdSkel rule (one line with the prim path and the problem).
        UnsupportedError: Nothing the format can hold (a skeleton without joints, only blend shapes).
    """

    _check_options(options)


    messages: list = []
    try:
        with captured_usd_diagnostics(messages):
            scene = _read(Path(path), options)
    except Tf.ErrorException as error:  # a corrupt crate value that fails on its lazy read
        raise InputError(f"USD cannot read a value of the stage: {tf_message(error)}", file=str(path),
                         code="usd.value") from None
    said = tuple(f"/: usd.diagnostic: USD {kind}: {text}" for kind, text, _ in dict.fromkeys(messages)
                 if kind != "status")
    return dataclasses.replace(scene, warnings=scene.warnings + said) if said else scene


def _read(path: Path, options: ReadOptions) -> UsdSkelScene:
    """:func:`read` inside the capture of USD's diagnostics."""
    reader = _Reader(path, options)
    UsdGeom, UsdSkel = reader.UsdGeom, reader.UsdSkel
    stage = reader.stage
    reader.check_binding_api()
    reader.check_joint_counts()

    groups: dict[str, _SkelWork] = {}
    for prim, skel_prim in reader.skinnable_prims():
        key = str(skel_prim.GetPath())  # a Skeleton: _bound_skeleton refuses anything else
        if key not in groups:
            groups[key] = _SkelWork(skel_prim, reader.check_skeleton(skel_prim))
        groups[key].targets.append(prim)

    selected = [str(s) for s in options.skeletons]
    for wanted in selected:
        if wanted not in groups:
            known = ", ".join(groups) or "none"
            raise OptionsError(f"no bound Skeleton at '{wanted}' (bound skeletons: {known})", file=reader.file)
    keys = [k for k in groups if not selected or k in selected]
    if options.clips:
        # A UsdSkel clip is named after its Skeleton prim (spec: Clips); --clips selects by that name.
        clip_names = {k: groups[k].skel_prim.GetName() for k in keys}
        for wanted in (str(c) for c in options.clips):
            if wanted not in clip_names.values():
                known = ", ".join(repr(n) for n in clip_names.values()) or "none"
                raise OptionsError(f"no clip named {wanted!r} (clips are named after their Skeleton prims; "
                                   f"known: {known})", file=reader.file, location="/")
        keys = [k for k in keys if clip_names[k] in {str(c) for c in options.clips}]
    if not keys:
        raise UnsupportedError("no skinned mesh bound to a Skeleton was found", file=reader.file,
                               location="/", code="usdskel.nothing")

    animations, references, methods = [], [], []
    claimed_roots = {"targets": {str(p.GetPath()) for w in groups.values() for p in w.targets}, "roots": set()}
    prim_paths = _animation_paths(keys)
    for key in keys:
        work = groups[key]
        skel_prim = work.skel_prim
        location = key
        skel_query = reader.cache.GetSkelQuery(UsdSkel.Skeleton(skel_prim))
        if not skel_query:
            raise reader.error("UsdSkel cannot build a query for this skeleton (check its joints and "
                               "transforms)", location, "usdskel.skeleton.invalid")
        if not skel_query.HasRestPose() and not skel_query.GetAnimQuery():
            raise reader.error("the skeleton has neither restTransforms nor an animation", location,
                               "usdskel.restTransforms.missing")
        anim_query = skel_query.GetAnimQuery()
        if anim_query:
            reader.check_animation(anim_query.GetPrim(), work.joints)
            anim_joints = set(str(j) for j in anim_query.GetJointOrder())
            if not skel_query.HasRestPose() and not set(work.joints) <= anim_joints:
                raise reader.error("restTransforms is missing and the animation does not drive every joint",
                                   f"{location}.restTransforms", "usdskel.restTransforms.missing")

        codes = _time_samples(reader, skel_query, skel_prim)
        if options.time_range is not None:
            start_code, end_code = (float(v) for v in options.time_range)
            if codes and (end_code < codes[0] or start_code > codes[-1]):
                # Sampling there would bake held end poses only: refuse, naming both ranges.
                raise OptionsError(f"the frame range {start_code:g}..{end_code:g} lies outside the "
                                   f"animation's time codes {codes[0]:g}..{codes[-1]:g}",
                                   file=reader.file, location=location)
            keys_in = [c for c in codes if start_code <= c <= end_code]
            codes = sorted(set(keys_in) | {start_code, end_code})
        elif codes:
            start_code, end_code = codes[0], codes[-1]
        else:
            start_code = end_code = (float(stage.GetStartTimeCode()) if stage.HasAuthoredTimeCodeRange() else 0.0)
            codes = [start_code]
        sampler = SkeletonSampler(reader, skel_query, skel_prim, start_code, end_code)
        work.codes, work.anim_query = list(codes), skel_query.GetAnimQuery()

        bound = _bind_targets(reader, work, skel_query, start_code)
        if not work.joints:
            shaped = [str(t.GetPath()) for t in work.targets
                      if UsdSkel.BindingAPI(t).GetBlendShapesAttr().HasAuthoredValue()]
            if shaped:
                raise UnsupportedError(f"the skeleton has no joints; its meshes ({', '.join(shaped[:3])}) are "
                                       "deformed by blend shapes only, which Virtual Bones cannot hold",
                                       file=reader.file, location=location, code="usdskel.blendShapesOnly")
            raise reader.error("the skeleton has no joints", f"{location}.joints", "usdskel.joints.empty")
        if not bound:
            raise UnsupportedError("no mesh bound to this skeleton can be converted (see the warnings)",
                                   file=reader.file, location=location, code="usdskel.nothing")
        bones = work.joints
        loose = _loose_gprims(reader, bound, claimed_roots, start_code,
                              method=bound[0].method, first_bone=len(work.joints))
        if loose:
            sampler.extra_prims = [b.prim for b in loose]
            bones = work.joints + tuple(str(b.prim.GetPath()).lstrip("/") for b in loose)
            bound = bound + loose
        tcps = reader.tcps
        clip = AnimationClip(name=skel_prim.GetName(), start_time=start_code / tcps, end_time=end_code / tcps,
                             sample=sampler, native_rate=_native_rate(codes, tcps), loop=None,
                             key_times=np.asarray(codes, dtype=np.float64) / tcps)
        meshes, lods = _levels(reader, prim_paths[key], [b.mesh for b in bound])
        animations.append(SkinnedAnimation(
            name=skel_prim.GetName(), path=prim_paths[key], bones=bones, clips=(clip,),
            meshes=meshes, source=reader.file, lods=lods,
            bind_transforms=_with_identity(bind_transforms(UsdSkel.Skeleton(skel_prim), len(work.joints)),
                                           len(bones) - len(work.joints)),
            bone_parents=_joint_parents(work.joints) + (-1,) * (len(bones) - len(work.joints))))
        references.append((sampler, bound, skel_query))
        methods.append(tuple(b.method for b in bound))

    def reference(animation_index: int, mesh_index: int, times) -> tuple:
        sampler, bound, skel_query = references[animation_index]
        if bound[mesh_index].loose:
            return _loose_reference(sampler, bound[mesh_index], times)
        return _usdskel_reference(reader, sampler, skel_query, bound[mesh_index], times)

    default = stage.GetDefaultPrim()
    default_name = default.GetName() if default else (animations[0].path.split("/")[1] or "VirtualBones")
    return UsdSkelScene(
        animations=tuple(animations), up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)), time_codes_per_second=reader.tcps,
        default_prim=default_name, warnings=tuple(reader.warnings), source=reader.file,
        reference=reference, skinning_methods=tuple(methods))


def _levels(reader: _Reader, animation_path: str, meshes: list) -> tuple:
    """The meshes with their level of detail and the source's UsdLod root (spec/virtual-bones.md 20.3).

    The meshes bound to one skeleton that lie under one LODRootAPI prim keep it: level = the root's
    child they sit under, thresholds from its LODScreenSizeHeuristic (the rules the reader applies,
    vbusd.io.usd_lod). Where the levels break a rule (another heuristic, an empty level, meshes
    partly outside the root), they convert as level-0 meshes, with a warning naming the rule.
    """

    findings, levels, lods = levels_of(reader.stage, animation_path, [m.path for m in meshes])
    if findings:
        reader.warn(str(findings[0].location), f"levels of detail not kept ({findings[0].code}: "
                    f"{findings[0].message}); every mesh converts as level 0")
        return tuple(meshes), None
    if lods is None:
        return tuple(meshes), None
    return tuple(dataclasses.replace(m, lod=int(level)) for m, level in zip(meshes, levels)), lods


def _with_identity(binds, extra: int):
    """Bind transforms with ``extra`` identities appended (an extra bone's matrix is its world
    transform: J = M), or None."""
    if binds is None or extra == 0:
        return binds
    return np.concatenate([binds, np.broadcast_to(np.eye(4), (extra, 4, 4))])


def _loose_gprims(reader: _Reader, bound: list, claimed: dict, start_code: float, method: str,
                  first_bone: int) -> list:
    """Meshes (and implicit gprims) under the SkelRoots of ``bound`` that no binding reaches.

    Rule (spec: usd-conversion.md, Meshes no binding reaches): a visible, non-guide gprim under a
    SkelRoot whose skeleton is converted, that no skeleton binding deforms, is what every renderer
    shows where its own transform puts it. It becomes a mesh of the first converted skeleton of
    that SkelRoot, bound with weight 1 to an extra bone whose transform is the prim's
    local-to-world transform at every time (constant when nothing animates it); its rest points
    are its own points at the clip's first time code. Each SkelRoot's loose gprims go to one
    skeleton (``claimed["roots"]`` records the roots already handled).
    """
    UsdGeom, Usd = reader.UsdGeom, reader.Usd
    roots = []
    for b in bound:
        root = reader._skel_root(b.prim)
        if root is not None and str(root.GetPath()) not in claimed["roots"] and root not in roots:
            roots.append(root)
    time = Usd.TimeCode(start_code)
    result = []
    for root in roots:
        claimed["roots"].add(str(root.GetPath()))
        # UsdSkel lists every prim bound to a skeleton as a target, even without influences (it
        # deforms none of those): only targets with joint influences or blend shapes are skinned.
        skinned = {path for path, (_, query) in reader.targets_of_root(root).items()
                   if query.HasJointInfluences() or query.HasBlendShapes()} | claimed["targets"]
        for prim in Usd.PrimRange(root, reader.predicate):
            location = str(prim.GetPath())
            if not prim.IsA(UsdGeom.Gprim) or location in skinned:
                continue
            imageable = UsdGeom.Imageable(prim)
            if imageable.ComputeVisibility(time) == UsdGeom.Tokens.invisible or \
                    imageable.ComputePurpose() == UsdGeom.Tokens.guide:
                continue
            implicit = None if prim.IsA(UsdGeom.Mesh) else implicit_surface(reader, prim, time)
            if implicit is not None:
                points, counts, fvi = implicit
                normals, n_interp = None, "vertex"
            elif prim.IsA(UsdGeom.Mesh):
                mesh = UsdGeom.Mesh(prim)
                points = np.asarray(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
                counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
                fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
                if points.shape[0] == 0 or counts.sum() != fvi.size or \
                        (fvi.size and (fvi.min() < 0 or fvi.max() >= points.shape[0])):
                    reader.warn(location, "is a Mesh no binding reaches with no points or inconsistent topology; "
                                "not converted")
                    continue
                if not _finite(points):
                    raise reader.error("points are not finite", f"{location}.points", "usdskel.points.nonFinite")
                normals, n_interp = _normals(reader, mesh, counts, fvi, points.shape[0], time)
            else:
                reader.warn(location, f"is a {prim.GetTypeName()} no binding reaches and not a surface; "
                            "not converted")
                continue
            bone = first_bone + len(result)
            count = points.shape[0]
            mesh_data = SkinnedMesh(
                path=location, points=points, face_vertex_counts=counts, face_vertex_indices=fvi,
                bone_indices=np.full((count, 1), bone, dtype=np.int64), bone_weights=np.ones((count, 1)),
                normals=normals, normals_interpolation=n_interp, source_path=location)
            result.append(_Bound(prim, mesh_data, None, method, np.arange(0), implicit_points=points if implicit
                                 is not None else None, loose=True))
            moving = UsdGeom.Xformable(prim).TransformMightBeTimeVarying() or any(
                UsdGeom.Xformable(a).TransformMightBeTimeVarying() for a in _ancestors(prim) if a.IsA(UsdGeom.Xformable))
            reader.warn(location, f"is under SkelRoot {root.GetPath()} but no skeleton binding reaches it; converted "
                        f"as a rigid mesh following its own {'animated' if moving else 'fixed'} transform "
                        f"(an extra bone), as renderers show it")
    return result


def _ancestors(prim) -> list:
    found, node = [], prim.GetParent()
    while node and not node.IsPseudoRoot():
        found.append(node)
        node = node.GetParent()
    return found


def _loose_reference(sampler: SkeletonSampler, bound: _Bound, times) -> tuple:
    """A loose gprim's points (and normals) placed by USD's own transform evaluation
    (``UsdGeom.XformCache.GetLocalToWorldTransform``) at source times (seconds)."""
    codes = sampler.codes(np.atleast_1d(np.asarray(times, dtype=np.float64))).tolist()
    index = sampler.extra_prims.index(bound.prim)
    worlds = sampler.extra_world(codes)[:, index]                       # row-vector (n, 4, 4)
    points = np.asarray(bound.mesh.points, dtype=np.float64)
    placed = np.einsum("vi,nij->nvj", points, worlds[:, :3, :3]) + worlds[:, None, 3, :3]
    normals = None
    if bound.mesh.normals is not None:
        inverse_t = np.linalg.inv(worlds[:, :3, :3])
        normals = np.einsum("vi,nji->nvj", np.asarray(bound.mesh.normals, dtype=np.float64), inverse_t)
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-30)
    return placed, normals


def _animation_paths(skeleton_paths: list) -> dict:
    """Prim path of each skeleton's animation prim: the Skeleton's own path, unless two converted
    skeletons share a name (textures are named after the prim); then ``<parent>/<parentName>_<name>``,
    numbered if that still clashes."""
    names = [p.rsplit("/", 1)[-1] for p in skeleton_paths]
    result, taken = {}, set()
    for path, name in zip(skeleton_paths, names):
        chosen = path
        if names.count(name) > 1:
            parent = path.rsplit("/", 1)[0]
            stem = f"{parent.rsplit('/', 1)[-1] or 'Root'}_{name}"
            chosen, number = f"{parent}/{stem}", 1
            while chosen.rsplit("/", 1)[-1] in taken:
                number += 1
                chosen = f"{parent}/{stem}_{number}"
        taken.add(chosen.rsplit("/", 1)[-1])
        result[path] = chosen
    return result


def _bind_targets(reader: _Reader, work: _SkelWork, skel_query, start_code: float) -> list:
    """Turn every prim bound to one skeleton into a :class:`SkinnedMesh` (or a warning)."""
    UsdSkel, UsdGeom, Usd = reader.UsdSkel, reader.UsdGeom, reader.Usd
    skel_path = str(work.skel_prim.GetPath())
    bound = []
    target_paths = {str(t.GetPath()) for t in work.targets}
    for prim in work.targets:
        location = str(prim.GetPath())
        binding = UsdSkel.BindingAPI(prim)
        shapes = binding.GetBlendShapesAttr()
        has_shapes = bool(shapes and shapes.HasAuthoredValue() and shapes.Get())
        source = reader.influence_source(prim)
        if not prim.IsA(UsdGeom.Gprim) and any(p.startswith(location + "/") for p in target_paths):
            continue   # an Xform whose rigid binding the gprims below it inherit (converted there)
        if source is None:
            reader.warn(location, "is deformed by blend shapes only (no joint influences); blend shapes "
                        "cannot be held by Virtual Bones, so it is not converted")
            continue
        time = Usd.TimeCode(start_code)
        implicit = None
        if not prim.IsA(UsdGeom.Mesh):
            implicit = implicit_surface(reader, prim, time)
            if implicit is None:
                kind = prim.GetTypeName() or "typeless prim"
                reader.warn(location, f"is a skinned {kind}, not a Mesh; Virtual Bones binds meshes only, so it "
                            "is not converted (bake it with UsdSkel.BakeSkinning or convert it to a Mesh)")
                continue
        mesh = UsdGeom.Mesh(prim)
        points_attr = mesh.GetPointsAttr()
        if implicit is not None:
            points = implicit[0]
        else:
            points = np.asarray(points_attr.Get(time) or [], dtype=np.float64).reshape(-1, 3)
        if points.shape[0] == 0:
            reader.warn(location, "has no points; it is not converted")
            continue
        if not _finite(points):
            bad = int(np.argwhere(~np.isfinite(points))[0][0])
            raise reader.error(f"point {bad} is not finite", f"{location}.points", "usdskel.points.nonFinite")
        if implicit is not None:
            counts, fvi = implicit[1], implicit[2]
        else:
            if points_attr.GetNumTimeSamples() > 1:
                reader.warn(location, f"points are time-sampled; the rest shape at time code {start_code:g} is used")
            if _normals_attr(reader, mesh).GetNumTimeSamples() > 1:
                reader.warn(location, f"normals are time-sampled; the rest normals at time code {start_code:g} are used")
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
            fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
        if counts.sum() != fvi.size or (fvi.size and (fvi.min() < 0 or fvi.max() >= points.shape[0])):
            raise reader.error(f"faceVertexCounts sum to {int(counts.sum())} and faceVertexIndices has "
                               f"{fvi.size} entries for {points.shape[0]} points: inconsistent topology",
                               location, "usdskel.mesh.topology")
        # Our own checks first: UsdSkel only prints warnings for these.
        joint_map = _joint_map(reader, _joints_source(reader, prim), work.joints)
        indices, weights, interp = _read_influences(reader, source, points.shape[0], joint_map.size)

        query = _skinning_query(reader, prim, skel_path)
        if query is None:
            raise reader.error("UsdSkel does not treat this prim as a skinning target of "
                               f"{skel_path} (check its joint influences)", location, "usdskel.binding")
        method = str(query.GetSkinningMethod())
        if has_shapes:
            reader.warn(location, "has blend shapes (skel:blendShapes); Virtual Bones cannot hold them, so "
                        "only its joint skinning is converted; " + _blend_shape_loss(
                            reader, prim, query, work, points))
        geom_bind = _matrix(query.GetGeomBindTransform(time))
        if not _finite(geom_bind) or abs(np.linalg.det(geom_bind[:3, :3])) < 1e-12:
            raise reader.error("primvars:skel:geomBindTransform is singular or not finite",
                               f"{location}.primvars:skel:geomBindTransform", "usdskel.geomBindTransform")
        bind_points = points @ geom_bind[:3, :3] + geom_bind[3, :3]
        normals, n_interp = (None, "vertex") if implicit is not None else \
            _normals(reader, mesh, counts, fvi, points.shape[0], time)
        if normals is not None:
            normal_matrix = np.linalg.inv(geom_bind[:3, :3]).T  # row-vector inverse transpose
            normals = normals @ normal_matrix
            lengths = np.linalg.norm(normals, axis=1, keepdims=True)
            normals = np.divide(normals, lengths, out=np.zeros_like(normals), where=lengths > 0)
        skinned = SkinnedMesh(
            path=location, points=bind_points, face_vertex_counts=counts, face_vertex_indices=fvi,
            bone_indices=joint_map[indices], bone_weights=weights, normals=normals,
            normals_interpolation=n_interp, source_path=location)
        bound.append(_Bound(prim, skinned, query, method, joint_map,
                            implicit_points=None if implicit is None else points))
        if implicit is not None:
            detail = "" if prim.IsA(UsdGeom.Cube) else f", {IMPLICIT_SEGMENTS} segments around its axis"
            reader.warn(location, f"is a {prim.GetTypeName()}, converted as a Mesh of {points.shape[0]} points "
                        f"({int(counts.size)} faces{detail}) bound as UsdSkel binds it")
    return bound


IMPLICIT_SEGMENTS = 10
"""Segments around the axis (and half-rings per hemisphere x 2 for spheres) of a tessellated
Sphere, Cylinder, Cone or Capsule: Hydra's default resolution (spec: Rigid bindings)."""


def _revolution(rings: list, axis: str) -> tuple:
    """Points, counts and indices of a closed surface of revolution about ``axis``.

    Args:
        rings: ``(radius, height)`` from bottom to top; a radius of 0 is a pole (one point).
        axis: ``X``, ``Y`` or ``Z``.
    """
    n = IMPLICIT_SEGMENTS
    angles = 2.0 * np.pi * np.arange(n) / n
    points, starts = [], []
    for radius, height in rings:
        starts.append(len(points))
        if radius == 0.0:
            points.append((0.0, 0.0, height))
        else:
            points.extend((radius * np.cos(a), radius * np.sin(a), height) for a in angles)
    faces = []
    for k in range(len(rings) - 1):
        a, b = starts[k], starts[k + 1]
        pole_a, pole_b = rings[k][0] == 0.0, rings[k + 1][0] == 0.0
        for j in range(n):
            j1 = (j + 1) % n
            if pole_a:
                faces.append((a, b + j1, b + j))
            elif pole_b:
                faces.append((a + j, a + j1, b))
            else:
                faces.append((a + j, a + j1, b + j1, b + j))
    # Closing caps for rings that end without a pole (cylinders, the cone's base).
    if rings[0][0] != 0.0:
        faces.append(tuple(starts[0] + j for j in reversed(range(n))))
    if rings[-1][0] != 0.0:
        faces.append(tuple(starts[-1] + j for j in range(n)))
    p = np.array(points, dtype=np.float64)
    order = {"X": [2, 0, 1], "Y": [1, 2, 0], "Z": [0, 1, 2]}[axis]   # rotations taking Z to the axis
    p = p[:, order]
    counts = np.array([len(f) for f in faces], dtype=np.int64)
    return p, counts, np.array([i for f in faces for i in f], dtype=np.int64)


def implicit_surface(reader: _Reader, prim, time) -> Optional[tuple]:
    """A Cube, Sphere, Cylinder, Cone or Capsule as (points, faceVertexCounts, faceVertexIndices)
    in the prim's space, or None for other prim types (spec: usd-conversion.md, Rigid bindings).

    Cube: its 8 corners, 6 quads. The others: :data:`IMPLICIT_SEGMENTS` segments around the axis;
    a sphere or a capsule's hemispheres get ``IMPLICIT_SEGMENTS // 2`` bands from pole to equator.
    Faces wind counterclockwise seen from outside (USD's rightHanded orientation).
    """
    UsdGeom = reader.UsdGeom

    def value(attr, default):
        got = attr.Get(time) if attr else None
        return float(default if got is None else got)

    if prim.IsA(UsdGeom.Cube):
        h = 0.5 * value(UsdGeom.Cube(prim).GetSizeAttr(), 2.0)
        corners = np.array([(x, y, z) for x in (-h, h) for y in (-h, h) for z in (-h, h)])
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        return corners, np.full(6, 4, dtype=np.int64), np.array(quads, dtype=np.int64).reshape(-1)
    half = IMPLICIT_SEGMENTS // 2
    if prim.IsA(UsdGeom.Sphere):
        r = value(UsdGeom.Sphere(prim).GetRadiusAttr(), 1.0)
        bands = np.linspace(-np.pi / 2, np.pi / 2, 2 * half + 1)
        rings = [(0.0 if k in (0, 2 * half) else r * np.cos(a), r * np.sin(a)) for k, a in enumerate(bands)]
        return _revolution(rings, "Z")
    for kind in (UsdGeom.Cylinder, UsdGeom.Cone, UsdGeom.Capsule):
        if not prim.IsA(kind):
            continue
        shape = kind(prim)
        r = value(shape.GetRadiusAttr(), 1.0 if kind is not UsdGeom.Capsule else 0.5)
        height = value(shape.GetHeightAttr(), 2.0 if kind is not UsdGeom.Capsule else 1.0)
        axis = str(shape.GetAxisAttr().Get(time) or "Z")
        if kind is UsdGeom.Cylinder:
            rings = [(0.0, -height / 2), (r, -height / 2), (r, height / 2), (0.0, height / 2)]
        elif kind is UsdGeom.Cone:
            rings = [(0.0, -height / 2), (r, -height / 2), (0.0, height / 2)]
        else:
            angles = np.linspace(0.0, np.pi / 2, half + 1)
            bottom = [(r * np.sin(a), -height / 2 - r * np.cos(a)) for a in angles]
            top = [(r * np.cos(a), height / 2 + r * np.sin(a)) for a in angles]
            rings = [(0.0, bottom[0][1])] + bottom[1:] + top[:-1] + [(0.0, top[-1][1])]
        return _revolution(rings, axis)
    return None


def _blend_shape_loss(reader: _Reader, prim, query, work: _SkelWork, points: np.ndarray) -> str:
    """What dropping a mesh's blend shapes loses, in words (spec: usd-conversion.md, Meshes).

    UsdSkel's own ``BlendShapeQuery.ComputeDeformedPoints`` deforms the rest points with the
    animation's ``blendShapeWeights`` (remapped to the mesh's ``skel:blendShapes`` order, inbetweens
    included) at every key time code of the clip and every time sample of the weights inside it;
    the largest distance a point moves, in the mesh's own space before skinning, is the figure.
    """

    UsdSkel, Usd = reader.UsdSkel, reader.Usd
    rest = "the rest shape used is the points as authored (every blend shape weight 0)"
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
    count = shapes.GetNumBlendShapes() if shapes else 0
    anim = work.anim_query
    if count == 0:
        return rest
    point_indices = shapes.ComputeBlendShapePointIndices()
    offsets = shapes.ComputeSubShapePointOffsets()
    mapper = query.GetBlendShapeMapper()
    source = np.ascontiguousarray(points, dtype=np.float32)
    worst = (0.0, -1, 0.0)
    codes = list(work.codes or [0.0])
    if anim:   # the weights' own keys inside the clip (they blend linearly between keys)
        low, high = min(codes), max(codes)
        codes = sorted(set(codes) | {float(c) for c in anim.GetBlendShapeWeightTimeSamples() if low <= c <= high})
    for code in codes:
        weights = anim.ComputeBlendShapeWeights(Usd.TimeCode(code)) if anim else None
        if weights is None or len(weights) == 0:
            weights = Vt.FloatArray(count, 0.0)
        elif mapper is not None and not mapper.IsNull() and not mapper.IsIdentity():
            weights = mapper.Remap(weights)
        sub_weights, shape_indices, sub_indices = shapes.ComputeSubShapeWeights(weights)
        moved = Vt.Vec3fArray.FromNumpy(source.copy())
        if not shapes.ComputeDeformedPoints(sub_weights, shape_indices, sub_indices, point_indices, offsets, moved):
            continue
        distance = np.linalg.norm(np.asarray(moved, dtype=np.float64) - source, axis=1)
        point = int(np.argmax(distance)) if distance.size else -1
        if point >= 0 and distance[point] > worst[0]:
            worst = (float(distance[point]), point, float(code))
    if worst[0] == 0.0:
        return f"{rest}; their weights stay 0 over the clip, so nothing is lost"
    return (f"{rest}; over the clip the dropped blend shapes move a point by up to {worst[0]:.4g} scene units "
            f"(point {worst[1]}, time code {worst[2]:g})")


def _joints_source(reader: _Reader, prim):
    """The prim whose ``skel:joints`` (joint order) applies: the nearest ancestor-or-self with it
    authored (it is inherited, like the binding), else ``prim``."""
    node = prim
    while node and not node.IsPseudoRoot():
        attr = reader.UsdSkel.BindingAPI(node).GetJointsAttr()
        if attr and attr.HasAuthoredValue():
            return node
        node = node.GetParent()
    return prim


def _skinning_query(reader: _Reader, prim, skel_path: str):
    """UsdSkel's own SkinningQuery of ``prim`` (via UsdSkel.Cache bindings), or None."""
    root = reader._skel_root(prim)
    if root is None:
        return None
    entry = reader.targets_of_root(root).get(str(prim.GetPath()))
    if entry is None or entry[0] != skel_path:
        return None
    return entry[1]


def _usdskel_reference(reader: _Reader, sampler: SkeletonSampler, skel_query, bound: _Bound, times) -> tuple:
    """UsdSkel's skinned points and normals of one mesh in world space at source times (seconds).

    Points: ``SkinningQuery.ComputeSkinnedPoints`` (UsdSkel's own method: LBS or DQS, joint mapper
    and geomBindTransform included), then the Skeleton's local-to-world transform. Normals:
    ``UsdSkel.SkinNormals`` with the inverse-transpose matrices, as UsdSkel.BakeSkinning does,
    per face-vertex for faceVarying normals.
    """

    Usd, UsdSkel = reader.Usd, reader.UsdSkel
    query = bound.query
    mesh = reader.UsdGeom.Mesh(bound.prim)
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    points_attr = mesh.GetPointsAttr()
    # Time-sampled points (the converter keeps the first as the rest shape, with a warning):
    # UsdSkel skins the points of each time code, so the reference does too and the report shows
    # the difference.
    varying = bound.implicit_points is None and points_attr.GetNumTimeSamples() > 1
    rest = points_attr.Get(Usd.TimeCode(sampler.code(times[0]))) if bound.implicit_points is None else \
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(bound.implicit_points, dtype=np.float32))
    has_normals = bound.mesh.normals is not None
    if has_normals:
        indices, weights = query.ComputeJointInfluences()
        k = query.GetNumInfluencesPerComponent()
        ind = np.asarray(indices, dtype=np.int32).reshape(-1, k)
        wgt = np.asarray(weights, dtype=np.float32).reshape(-1, k)
        if ind.shape[0] == 1:  # constant (rigid) influences
            ind = np.repeat(ind, len(rest), axis=0)
            wgt = np.repeat(wgt, len(rest), axis=0)
        if bound.mesh.normals_interpolation == "faceVarying":
            ind, wgt = ind[bound.mesh.face_vertex_indices], wgt[bound.mesh.face_vertex_indices]
        vt_ind = Vt.IntArray.FromNumpy(np.ascontiguousarray(ind.reshape(-1)))
        vt_wgt = Vt.FloatArray.FromNumpy(np.ascontiguousarray(wgt.reshape(-1)))
        # Time-sampled normals, like points: UsdSkel skins each time code's own.
        normals_vary = _normals_attr(reader, mesh).GetNumTimeSamples() > 1
        raw_normals = _raw_normals(reader, mesh, bound, Usd.TimeCode(sampler.start_code))  # the converter's
        geom = np.linalg.inv(_matrix(query.GetGeomBindTransform())[:3, :3]).T
        geom3 = Gf.Matrix3d(*geom.reshape(-1).tolist())
        mapper = query.GetJointMapper()
        method = query.GetSkinningMethod()
    points_out = np.empty((times.size, len(rest), 3))
    normals_out = None
    for i, t in enumerate(times):
        code = sampler.code(t)
        xforms, world = sampler.usd_transforms(code)
        points = Vt.Vec3fArray(points_attr.Get(Usd.TimeCode(code)) if varying else rest)
        if not query.ComputeSkinnedPoints(xforms, points, Usd.TimeCode(code)):
            raise InputError(f"UsdSkel could not skin the points at time code {code:g}", file=reader.file,
                             location=str(bound.prim.GetPath()), code="usdskel.skinning")
        p = np.asarray(points, dtype=np.float64)
        points_out[i] = p @ world[:3, :3] + world[3, :3]
        if has_normals:
            identity = mapper is None or mapper.IsIdentity()
            # Meshes bound to one skeleton share these per time code: compute them once.
            key = (round(code, 9), None if identity else tuple(bound.joint_map.tolist()))
            joint3 = sampler.normal_memo.get(key)
            if joint3 is None:
                local = xforms if identity else mapper.RemapTransforms(xforms, Vt.Matrix4dArray(), 1)
                linear = np.asarray(local, dtype=np.float64).reshape(-1, 4, 4)[:, :3, :3]
                joint3 = sampler.normal_memo[key] = Vt.Matrix3dArray.FromNumpy(
                    np.ascontiguousarray(np.swapaxes(np.linalg.inv(linear), 1, 2)))
            raw = _raw_normals(reader, mesh, bound, Usd.TimeCode(code)) if normals_vary else raw_normals
            normals = Vt.Vec3fArray.FromNumpy(raw if raw is not None and raw.shape == raw_normals.shape
                                              else raw_normals)
            UsdSkel.SkinNormals(method, geom3, joint3, vt_ind, vt_wgt, k, normals)
            world_normal = sampler.normal_memo.get(("world", round(code, 9)))
            if world_normal is None:
                world_normal = sampler.normal_memo[("world", round(code, 9))] = np.linalg.inv(world[:3, :3]).T
            n = np.asarray(normals, dtype=np.float64) @ world_normal
            if normals_out is None:
                normals_out = np.empty((times.size,) + n.shape)
            normals_out[i] = n
    if normals_out is not None:  # normalized once for all times (per-time norms cost more than skinning)
        normals_out /= np.maximum(np.sqrt(np.einsum("nvi,nvi->nv", normals_out, normals_out))[..., None], 1e-30)
    return points_out, normals_out


def _normals_attr(reader: _Reader, mesh):
    """The attribute the normals come from: ``primvars:normals`` when authored, else ``normals``."""
    primvar = reader.UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("normals")
    return primvar.GetAttr() if primvar and primvar.HasAuthoredValue() else mesh.GetNormalsAttr()


def _raw_normals(reader: _Reader, mesh, bound: _Bound, time) -> Optional[np.ndarray]:
    """The mesh's authored normals at ``time``, expanded like the converter expands them (no geomBind)."""
    counts = bound.mesh.face_vertex_counts
    fvi = bound.mesh.face_vertex_indices
    saved = list(reader.warnings)
    normals, _ = _normals(reader, mesh, counts, fvi, bound.mesh.points.shape[0], time)
    reader.warnings[:] = saved
    return None if normals is None else np.asarray(normals, dtype=np.float32)


def _joint_parents(joints) -> tuple:
    """Each joint's parent joint index (spec 8.6), by path as UsdSkel's topology defines it; -1 for a root."""
    index = {str(j): i for i, j in enumerate(joints)}
    return tuple(index.get(str(j).rsplit("/", 1)[0], -1) if "/" in str(j) else -1 for j in joints)


def bind_transforms(skeleton, joint_count: int):
    """The joints' bind transforms in animation space (format 1.1 sockets), or None.

    The skinning matrices are ``inverse(bind_j) * jointSkel_j * W_skel`` (row vectors), so the
    joint's world transform ``jointSkel_j * W_skel`` (UsdSkel's ``ComputeJointWorldTransforms``) is
    ``bind_j * M_j``: in column-vector form ``J = M B`` with ``B = bind_j`` transposed
    (spec/usd-conversion.md, "Sockets").
    """
    value = skeleton.GetBindTransformsAttr().Get()
    if value is None or len(value) != joint_count:
        return None
    return np.transpose(np.array(value, dtype=np.float64).reshape(-1, 4, 4), (0, 2, 1)).copy()
