"""glTF 2.0 (.gltf, .glb) to Virtual Bones: skins, meshes and animations as SkinnedAnimations.

The normative mapping is spec/gltf-conversion.md; docs/converters/gltf.md is the user guide.
In short:

* one :class:`vbusd.format.model.SkinnedAnimation` per glTF skin; its bones are the skin's joints in
  ``skin.joints`` order and its skinning matrices are ``jointWorld(t) @ inverseBind`` in the space
  of the scene root, where ``jointWorld`` walks the full node hierarchy (non-joint ancestors
  included). The skinned mesh node's own transform is ignored, as glTF 2.0 (3.7.3.3) requires;
* one clip per glTF animation that moves a joint of the skin or an ancestor of one;
* one :class:`vbusd.format.model.SkinnedMesh` per primitive of every node that uses the skin, with the
  rest POSITION/NORMAL as stored and every JOINTS_n/WEIGHTS_n set merged; weights that do not sum
  to one renormalized as engines do (``ReadOptions.strict_weights`` refuses them instead);
* mesh nodes without a skin as rigid attachments: one influence on the joint above them, or on an
  extra bone (an animated non-joint node, or the root of a prop's tree), the node offset baked into
  the rest points (spec "Rigid attachments"); morph targets dropped with the largest displacement
  they cause stated in a warning;
* Y up, metres; 24 time codes per second; prim names made valid and unique by the rule of
  :func:`make_identifier` and :class:`NameAllocator`.

The container is read by :mod:`vbusd.io.gltf` (pygltflib parses it; GLB chunks, raw-JSON types
and bounds, URIs, base64 and buffer sizes are checked there) and accessors by
:mod:`vbusd.io.gltf_accessors`; everything else pygltflib does not check (indices, the node graph,
the skin and animation rules that Khronos' glTF-Validator reports as errors) is checked here. Every
problem raises :class:`vbusd.format.errors.InputError` with a JSON pointer.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vbusd.format.errors import InputError, OptionsError, UnsupportedError
from vbusd.format.model import AnimationClip, ReadOptions, SkinnedAnimation, SkinnedMesh, SourceScene
from vbusd.io.gltf import GLB_MAGIC, load
from vbusd.io.gltf_accessors import COMPONENT_NAMES, MODE_NAMES, AccessorReader, require_index, triangles

from vbusd.converters.gltf_animation import compose_trs, sample_channel

__all__ = ["NAME", "SUFFIXES", "TIME_CODES_PER_SECOND", "DEFAULT_RATE",
           "QUAT_UNIT_TOLERANCE", "WEIGHT_SUM_TOLERANCE", "make_identifier", "NameAllocator",
           "GltfScene", "native_rate", "sniff", "check_time_range", "read",
           "bind_transforms"]

NAME = "gltf"
"""Converter name (``vbusd convert --from gltf``)."""

SUFFIXES = (".gltf", ".glb")
"""File suffixes this converter reads."""

TIME_CODES_PER_SECOND = 24.0
"""The output stage's timeCodesPerSecond: time code = glTF seconds x 24."""

DEFAULT_RATE = 30.0
"""Rows per second proposed for a clip whose keys do not lie on a regular grid of 10..240 Hz."""

QUAT_UNIT_TOLERANCE = 5e-3
"""Rotation keys whose length differs from 1 by more than this get a warning (then normalized)."""

WEIGHT_SUM_TOLERANCE = 2e-7
"""Per non-zero weight: |sum - 1| may not exceed this times the non-zero count (glTF-Validator)."""

_IDENTIFIER_BAD = re.compile(r"[^A-Za-z0-9_]")

VIRTUAL_SKIN = -1
"""Key of the animation made for mesh nodes that animations move when the file converts no skin
(spec: Rigid attachments): its bones are only extra bones, and its prim is ``/<root>/Nodes_Anim``."""


# ------------------------------------------------------------------------------------------------
# Names
# ------------------------------------------------------------------------------------------------


def make_identifier(name, fallback: str) -> str:
    """Make a valid USD prim name (ASCII identifier) from a glTF name.

    Rule (spec/gltf-conversion.md, "Names"): every character other than ``A-Z a-z 0-9 _`` becomes
    ``_``; an empty or missing name becomes ``fallback``; a name starting with a digit gets a
    leading ``_``.

    Args:
        name: The glTF ``name`` (may be None or not a string).
        fallback: Name used when ``name`` is empty, e.g. ``node7``.
    """
    text = name if isinstance(name, str) else ""
    text = _IDENTIFIER_BAD.sub("_", text)
    if not text:
        text = fallback
    if text[0].isdigit():
        text = "_" + text
    return text


class NameAllocator:
    """Hands out unique names within one scope: the second ``Foo`` becomes ``Foo_1``, then ``Foo_2``."""

    def __init__(self) -> None:
        self._used: set[str] = set()

    def take(self, name: str) -> str:
        """Return ``name``, or ``name_<k>`` with the smallest k >= 1 not yet taken; mark it taken."""
        candidate, k = name, 0
        while candidate in self._used:
            k += 1
            candidate = f"{name}_{k}"
        self._used.add(candidate)
        return candidate


# ------------------------------------------------------------------------------------------------
# Scene conversion
# ------------------------------------------------------------------------------------------------


@dataclass
class _Channel:
    node: int
    path: str            # translation | rotation | scale
    keys: np.ndarray     # (k,)
    values: np.ndarray   # (k, c) or (k, 3, c) for CUBICSPLINE
    interpolation: str


@dataclass
class _Animation:
    index: int
    name: str
    channels: list = field(default_factory=list)   # of _Channel (T/R/S only)
    weight_channels: dict = field(default_factory=dict)   # node -> _Channel of morph weights (or None)
    start: float = 0.0
    end: float = 0.0


@dataclass
class _Attachment:
    node: int            # the mesh node (no skin)
    bone: int            # the node it follows rigidly: a joint, or an animated node (extra bone)
    rel: np.ndarray      # (4, 4) rest transform from ``bone``'s space to ``node``'s (constant)


@dataclass(frozen=True)
class GltfScene(SourceScene):
    """A :class:`SourceScene` that also says which meshes had their weights renormalized.

    Attributes:
        raw_weights: Per animation, per mesh: ``(weights, joints)`` as stored, for a mesh whose
            weights did not sum to one (spec: Meshes, "Weights"), else None. ``vbusd convert``
            reports the distance renormalizing moves their vertices.
    """

    raw_weights: tuple = ()


def _float_list(value, length: int, pointer: str, file: str):
    """A node's matrix/translation/rotation/scale as float64, or None when absent.

    The raw JSON checks (:data:`vbusd.io.gltf._TYPES`) have made it an array of finite numbers; its length is
    checked here.
    """
    if value is None:
        return None
    if len(value) != length:
        raise InputError(f"expected {length} numbers, found {value!r}", file=file, location=pointer,
                         code="gltf.node.transform")
    return np.array(value, dtype=np.float64)


class _Converter:
    """Builds a SourceScene from a loaded glTF document; one instance per read()."""

    def __init__(self, gltf, buffers: list, file: str, options: ReadOptions) -> None:
        self.gltf = gltf
        self.file = file
        self.options = options
        self.reader = AccessorReader(gltf, buffers, file)
        self.warnings: list[str] = []
        self.quantized = "KHR_mesh_quantization" in (gltf.extensionsUsed or [])
        self.renormalized: dict = {}
        self._clip_sources: dict = {}   # id(AnimationClip) -> _Animation it was made from
        """(mesh, primitive) -> (raw weights, joints) of primitives whose weights were renormalized."""

    def warn(self, message: str) -> None:
        """Record a one-line warning once."""
        if message not in self.warnings:
            self.warnings.append(message)

    def fail(self, message: str, location: str, code: str) -> InputError:
        """An InputError about this file (the caller raises it)."""
        return InputError(message, file=self.file, location=location, code=code)

    # -- nodes -----------------------------------------------------------------------------------

    def read_nodes(self) -> None:
        """Check every node; compute parents, rest local matrices and rest TRS."""
        nodes = self.gltf.nodes
        n = len(nodes)
        self.parent = [-1] * n
        self.rest_local = np.zeros((n, 4, 4))
        self.rest_trs: list = [None] * n
        self.has_matrix = [False] * n
        for i, node in enumerate(nodes):
            where = f"/nodes/{i}"
            children = node.children or []   # an array of integers (raw JSON checks)
            for k, child in enumerate(children):
                require_index(child, n, f"{where}/children/{k}", self.file, "node")
                if self.parent[child] != -1:
                    raise self.fail(f"node {child} is already a child of node {self.parent[child]}; "
                                    "a node may have only one parent", f"{where}/children/{k}",
                                    "gltf.node.parents")
                self.parent[child] = i
            if node.mesh is not None:
                require_index(node.mesh, len(self.gltf.meshes), f"{where}/mesh", self.file, "mesh")
            if node.skin is not None:
                require_index(node.skin, len(self.gltf.skins), f"{where}/skin", self.file, "skin")
            matrix = _float_list(node.matrix, 16, f"{where}/matrix", self.file)
            t = _float_list(node.translation, 3, f"{where}/translation", self.file)
            r = _float_list(node.rotation, 4, f"{where}/rotation", self.file)
            s = _float_list(node.scale, 3, f"{where}/scale", self.file)
            if matrix is not None:
                if t is not None or r is not None or s is not None:
                    raise self.fail("a node has either matrix or translation/rotation/scale, not "
                                    "both", f"{where}/matrix", "gltf.node.transform")
                m = matrix.reshape(4, 4).T   # glTF is column-major
                if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
                    raise self.fail(f"matrix is not affine (last row {m[3].tolist()})",
                                    f"{where}/matrix", "gltf.node.transform")
                m = m.copy()
                m[3] = (0.0, 0.0, 0.0, 1.0)
                self.rest_local[i] = m
                self.has_matrix[i] = True
                continue
            t = np.zeros(3) if t is None else t
            s = np.ones(3) if s is None else s
            if r is None:
                r = np.array([0.0, 0.0, 0.0, 1.0])
            else:
                norm = float(np.linalg.norm(r))
                if norm == 0.0:
                    raise self.fail("rotation is a zero quaternion", f"{where}/rotation",
                                    "gltf.node.transform")
                if abs(norm - 1.0) > QUAT_UNIT_TOLERANCE:
                    self.warn(f"{where}/rotation: quaternion of length {norm:.6g} normalized")
                r = r / norm
            self.rest_trs[i] = (t, r, s)
            self.rest_local[i] = compose_trs(t, r, s)
        # Loops: with at most one parent per node, a cycle shows as a walk up that returns.
        state = [0] * n   # 0 unvisited, 1 on the current walk, 2 known to reach a root
        for start in range(n):
            walk, node = [], start
            while node != -1 and state[node] == 0:
                state[node] = 1
                walk.append(node)
                node = self.parent[node]
            if node != -1 and state[node] == 1:
                cycle = walk[walk.index(node):]
                chain = " -> ".join(str(c) for c in reversed(cycle + [node]))
                raise self.fail(f"node hierarchy has a loop: {chain}",
                                f"/nodes/{self.parent[node]}/children", "gltf.node.loop")
            for w in walk:
                state[w] = 2
        # Depths, each node's computed from its parent's (linear time, even for long chains).
        self.depth = [-1] * n
        for i in range(n):
            chain, node = [], i
            while node != -1 and self.depth[node] == -1:
                chain.append(node)
                node = self.parent[node]
            d = -1 if node == -1 else self.depth[node]
            for c in reversed(chain):
                d += 1
                self.depth[c] = d
        for si, scene in enumerate(self.gltf.scenes):
            for k, root in enumerate(scene.nodes or []):
                require_index(root, n, f"/scenes/{si}/nodes/{k}", self.file, "node")
                if self.parent[root] != -1:
                    raise self.fail(f"node {root} is listed as a scene root but is a child of node "
                                    f"{self.parent[root]}", f"/scenes/{si}/nodes/{k}",
                                    "gltf.scene")

    def bone_parents(self, bone_nodes) -> tuple:
        """Each bone's parent bone (spec 8.6): the nearest ancestor node that is a bone, else -1."""
        index = {node: b for b, node in enumerate(bone_nodes)}
        parents = []
        for node in bone_nodes:
            up = self.parent[node]
            while up != -1 and up not in index:
                up = self.parent[up]
            parents.append(index.get(up, -1))
        return tuple(parents)

    def ancestors_and_self(self, nodes) -> list:
        """Nodes and all their ancestors, parents before children."""
        found = set()
        for node in nodes:
            while node != -1 and node not in found:
                found.add(node)
                node = self.parent[node]
        return sorted(found, key=lambda x: (self.depth[x], x))

    def rest_world(self, node: int) -> np.ndarray:
        m = np.eye(4)
        while node != -1:
            m = self.rest_local[node] @ m
            node = self.parent[node]
        return m

    def node_label(self, index: int) -> str:
        name = self.gltf.nodes[index].name
        return f"node {index} {name!r}" if isinstance(name, str) and name else f"node {index}"

    # -- animations ------------------------------------------------------------------------------

    def _accessor_format(self, index: int, pointer: str, what: str, types: tuple,
                         components: tuple, normalized: tuple | None = None, code: str = "") -> None:
        acc, ctype, tname, _ = self.reader.header(index, pointer)
        ok = tname in types and ctype in components
        if ok and ctype != 5126 and normalized is not None:
            ok = bool(acc.normalized) in normalized
        if not ok:
            norm = " normalized" if acc.normalized else ""
            raise self.fail(f"{what} accessor {index} is {tname} {COMPONENT_NAMES.get(ctype)}{norm}; "
                            f"expected {'/'.join(types)} of "
                            f"{'/'.join(COMPONENT_NAMES[c] for c in components)}", pointer,
                            code or "gltf.accessor.format")

    def read_animations(self) -> list:
        """Check and decode every animation's T/R/S channels."""
        result = []
        for a, anim in enumerate(self.gltf.animations):
            where = f"/animations/{a}"
            samplers = anim.samplers or []
            channels = anim.channels or []
            decoded_inputs: dict[int, np.ndarray] = {}
            for s, sampler in enumerate(samplers):
                sw = f"{where}/samplers/{s}"
                interp = sampler.interpolation or "LINEAR"
                if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
                    raise self.fail(f"unknown interpolation {interp!r}", f"{sw}/interpolation",
                                    "gltf.animation.sampler")
                self._accessor_format(sampler.input, f"{sw}/input", "input", ("SCALAR",), (5126,),
                                      code="gltf.animation.input")
                keys = self.reader.read(sampler.input, f"{sw}/input")
                if keys[0] < 0:
                    raise self.fail(f"input accessor {sampler.input}: key 0 is negative "
                                    f"({keys[0]:g} s)", f"{sw}/input", "gltf.animation.input")
                steps = np.diff(keys)
                if np.any(steps <= 0):
                    k = int(np.nonzero(steps <= 0)[0][0]) + 1
                    raise self.fail(f"input accessor {sampler.input}: key {k} ({keys[k]:g} s) is not "
                                    f"greater than key {k - 1} ({keys[k - 1]:g} s)", f"{sw}/input",
                                    "gltf.animation.input")
                if interp == "CUBICSPLINE" and len(keys) < 2:
                    raise self.fail("CUBICSPLINE needs at least 2 keys, input has 1", sw,
                                    "gltf.animation.sampler")
                decoded_inputs[s] = keys
            record = _Animation(a, make_identifier(anim.name, f"animation{a}"))
            targets: dict[tuple, int] = {}
            all_keys = []
            for c, channel in enumerate(channels):
                cw = f"{where}/channels/{c}"
                s = require_index(channel.sampler, len(samplers), f"{cw}/sampler", self.file,
                                  "sampler")
                target = channel.target
                if target is None:
                    raise self.fail("channel has no target", cw, "gltf.animation.target")
                all_keys.append(decoded_inputs[s])
                if target.node is None:
                    continue   # targets defined by extensions only
                node = require_index(target.node, len(self.gltf.nodes), f"{cw}/target/node",
                                     self.file, "node")
                path = target.path
                if path not in ("translation", "rotation", "scale", "weights"):
                    raise self.fail(f"unknown target path {path!r}", f"{cw}/target/path",
                                    "gltf.animation.target")
                if (node, path) in targets:
                    raise self.fail(f"{self.node_label(node)} {path} is already animated by channel "
                                    f"{targets[(node, path)]}", cw, "gltf.animation.target")
                targets[(node, path)] = c
                if path == "weights":
                    # Morph weights are not baked; they are kept to measure what dropping the
                    # targets loses (spec: Meshes, "Morph targets").
                    sampler = samplers[s]
                    record.weight_channels[node] = self._read_weights_output(
                        node, decoded_inputs[s], sampler.interpolation or "LINEAR", sampler.output,
                        f"{where}/samplers/{s}/output")
                    continue
                if self.has_matrix[node]:
                    raise self.fail(f"{self.node_label(node)} has a matrix; animated nodes must use "
                                    "translation/rotation/scale", f"{cw}/target/node",
                                    "gltf.animation.target")
                sampler = samplers[s]
                interp = sampler.interpolation or "LINEAR"
                keys = decoded_inputs[s]
                record.channels.append(self._read_output(
                    node, path, keys, interp, sampler.output, f"{where}/samplers/{s}/output"))
            if all_keys:
                record.start = float(min(k[0] for k in all_keys))
                record.end = float(max(k[-1] for k in all_keys))
            result.append(record)
        return result

    def _read_weights_output(self, node: int, keys: np.ndarray, interp: str, output, pointer: str):
        """A morph ``weights`` channel as a _Channel of (k, targets) values, or None when its node
        has no mesh with targets or its output does not fit (a warning then says so)."""
        mesh = self.gltf.nodes[node].mesh
        prims = self.gltf.meshes[mesh].primitives if mesh is not None else None
        targets = len(prims[0].targets or []) if prims else 0
        if targets == 0:
            return None
        values = np.asarray(self.reader.read(output, pointer), dtype=np.float64).reshape(-1)
        per_key = 3 * targets if interp == "CUBICSPLINE" else targets
        if values.size != len(keys) * per_key:
            self.warn(f"{pointer}: morph weights output holds {values.size} values for {len(keys)} keys "
                      f"of {targets} targets; not measured")
            return None
        values = values.reshape(len(keys), 3, targets) if interp == "CUBICSPLINE" else \
            values.reshape(len(keys), targets)
        return _Channel(node, "weights", np.asarray(keys, dtype=np.float64), values, interp)

    def _read_output(self, node: int, path: str, keys: np.ndarray, interp: str, output,
                     pointer: str) -> _Channel:
        rotation = path == "rotation"
        width = 4 if rotation else 3
        # glTF 2.0 (3.11, animation sampler output table): translation and scale are FLOAT only;
        # rotation may also be a normalized integer. KHR_mesh_quantization extends mesh and morph
        # target attributes, not animation outputs (glTF-Validator reports integer translation or
        # scale keys as ANIMATION_SAMPLER_OUTPUT_ACCESSOR_INVALID_FORMAT).
        components = (5126, 5120, 5121, 5122, 5123) if rotation else (5126,)
        normalized = (True,) if rotation else None
        self._accessor_format(output, pointer, f"{path} output", ("VEC4" if rotation else "VEC3",),
                              components, normalized, code="gltf.animation.output")
        values = self.reader.read(output, pointer)
        expected = len(keys) * (3 if interp == "CUBICSPLINE" else 1)
        if len(values) != expected:
            raise self.fail(f"output accessor {output} has {len(values)} elements; {interp} with "
                            f"{len(keys)} input keys needs {expected}", pointer,
                            "gltf.animation.output")
        values = np.asarray(values, dtype=np.float64)
        if interp == "CUBICSPLINE":
            values = values.reshape(len(keys), 3, width)
        if rotation:
            points = values[:, 1] if interp == "CUBICSPLINE" else values
            norms = np.linalg.norm(points, axis=-1)
            if np.any(norms == 0):
                k = int(np.nonzero(norms == 0)[0][0])
                raise self.fail(f"rotation key {k} is a zero quaternion", pointer,
                                "gltf.animation.output")
            worst = float(np.max(np.abs(norms - 1.0)))
            if worst > QUAT_UNIT_TOLERANCE:
                self.warn(f"{pointer}: rotation keys are not unit quaternions (length off by up to "
                          f"{worst:.3g}); normalized")
            if interp == "CUBICSPLINE":
                values = values.copy()
                values[:, 1] = points / norms[:, None]
            else:
                values = points / norms[:, None]
        return _Channel(node, path, np.asarray(keys, dtype=np.float64), values, interp)

    # -- meshes ----------------------------------------------------------------------------------

    def mesh_label(self, index: int) -> str:
        name = self.gltf.meshes[index].name
        return (f"mesh {index} {name!r} (/meshes/{index})" if isinstance(name, str) and name
                else f"mesh {index} (/meshes/{index})")

    def read_primitive(self, m: int, p: int, joint_count: int, skin: int, rigid: bool = False) -> dict:
        """Decode one primitive of a skinned mesh; check it against a skin of ``joint_count`` joints.

        With ``rigid`` (a mesh attached to a node, spec: Rigid attachments) the primitive's
        ``JOINTS_n``/``WEIGHTS_n`` are not read: the caller binds every vertex to one bone.
        """
        where = f"/meshes/{m}/primitives/{p}"
        prim = self.gltf.meshes[m].primitives[p]
        mode = 4 if prim.mode is None else prim.mode
        if mode not in MODE_NAMES:
            raise self.fail(f"unknown primitive mode {mode!r}", f"{where}/mode", "gltf.mesh.mode")
        if mode not in (4, 5, 6):
            raise UnsupportedError(f"primitive mode {MODE_NAMES[mode]} ({mode}) cannot be a skinned "
                                   "mesh; only TRIANGLES, TRIANGLE_STRIP and TRIANGLE_FAN are",
                                   file=self.file, location=f"{where}/mode", code="gltf.mesh.mode")
        raw = prim.attributes
        # pygltflib turns a non-empty attributes object into an Attributes instance, an empty one
        # stays a dict.
        raw = raw if isinstance(raw, dict) else (vars(raw) if raw is not None else {})
        attributes = {k: v for k, v in raw.items() if v is not None}
        if "POSITION" not in attributes:
            raise self.fail("primitive has no POSITION", f"{where}/attributes", "gltf.mesh.attribute")
        aw = f"{where}/attributes"
        pos_types = (5126, 5120, 5121, 5122, 5123) if self.quantized else (5126,)
        self._accessor_format(attributes["POSITION"], f"{aw}/POSITION", "POSITION", ("VEC3",),
                              pos_types)
        points = np.asarray(self.reader.read(attributes["POSITION"], f"{aw}/POSITION"), np.float64)
        self._current_points = points
        count = len(points)
        normals = None
        if "NORMAL" in attributes:
            self._accessor_format(attributes["NORMAL"], f"{aw}/NORMAL", "NORMAL", ("VEC3",),
                                  (5126, 5120, 5122) if self.quantized else (5126,), (True,))
            normals = np.asarray(self.reader.read(attributes["NORMAL"], f"{aw}/NORMAL"), np.float64)
            if len(normals) != count:
                raise self.fail(f"NORMAL has {len(normals)} elements, POSITION {count}",
                                f"{aw}/NORMAL", "gltf.mesh.count")
        sets = sorted({int(k.split("_")[1]) for k in attributes
                       if re.fullmatch(r"(JOINTS|WEIGHTS)_\d+", k)})
        if rigid:
            sets = []
        elif 0 not in sets:
            raise self.fail(f"primitive of a skinned node (skin {skin}) has no JOINTS_0/WEIGHTS_0",
                            aw, "gltf.mesh.attribute")
        joints_all, weights_all = [], []
        for n in sets:
            for present, missing in ((f"JOINTS_{n}", f"WEIGHTS_{n}"), (f"WEIGHTS_{n}", f"JOINTS_{n}")):
                if missing not in attributes:
                    raise self.fail(f"{present} has no matching {missing}", aw,
                                    "gltf.mesh.attribute")
            jp, wp = f"{aw}/JOINTS_{n}", f"{aw}/WEIGHTS_{n}"
            self._accessor_format(attributes[f"JOINTS_{n}"], jp, f"JOINTS_{n}", ("VEC4",),
                                  (5121, 5123), (False,))
            self._accessor_format(attributes[f"WEIGHTS_{n}"], wp, f"WEIGHTS_{n}", ("VEC4",),
                                  (5126, 5121, 5123), (True,))
            joints = np.asarray(self.reader.read(attributes[f"JOINTS_{n}"], jp), np.int64)
            weights = np.asarray(self.reader.read(attributes[f"WEIGHTS_{n}"], wp), np.float64)
            for arr, pointer in ((joints, jp), (weights, wp)):
                if len(arr) != count:
                    raise self.fail(f"has {len(arr)} elements, POSITION {count}", pointer,
                                    "gltf.mesh.count")
            if np.any(weights < 0):
                v, c = (int(x[0]) for x in np.nonzero(weights < 0))
                raise self.fail(f"vertex {v} component {c}: weight {weights[v, c]:g} is negative",
                                wp, "gltf.skin.weights")
            used = weights > 0
            bad = used & (joints >= joint_count)
            if np.any(bad):
                v, c = (int(x[0]) for x in np.nonzero(bad))
                raise self.fail(f"vertex {v} component {c}: joint {joints[v, c]} is out of range "
                                f"(skin {skin} has {joint_count} joints)", jp, "gltf.skin.jointIndex")
            if np.any(joints >= joint_count):
                # Out-of-range joints with zero weight cannot move anything; index 0 is harmless.
                self.warn(f"{jp}: joints out of range with zero weight set to 0")
                joints = np.where(joints >= joint_count, 0, joints)
            joints_all.append(joints)
            weights_all.append(weights)
        if rigid:
            joints_all, weights_all = [np.zeros((count, 1), np.int64)], [np.ones((count, 1))]
        joints = np.concatenate(joints_all, axis=1)
        weights = np.concatenate(weights_all, axis=1)
        # Duplicate joints with weight in one vertex (glTF-Validator ACCESSOR_JOINTS_INDEX_DUPLICATE).
        keyed = np.where(weights > 0, joints, -1 - np.arange(joints.shape[1])[None, :])
        ordered = np.sort(keyed, axis=1)
        dup = np.any(ordered[:, 1:] == ordered[:, :-1], axis=1)
        if np.any(dup):
            v = int(np.nonzero(dup)[0][0])
            raise self.fail(f"vertex {v} lists joint {int(ordered[v][1:][ordered[v][1:] == ordered[v][:-1]][0])} "
                            "twice with non-zero weight", f"{aw}/JOINTS_0", "gltf.skin.jointIndex")
        if not rigid:
            weights, joints = self.normalize_weights(weights, joints, m, p, aw)
        # Topology.
        if prim.indices is not None:
            ip = f"{where}/indices"
            self._accessor_format(prim.indices, ip, "indices", ("SCALAR",), (5121, 5123, 5125),
                                  (False,))
            indices = np.asarray(self.reader.read(prim.indices, ip), np.int64)
            _, ctype, _, _ = self.reader.header(prim.indices, ip)
            restart = {5121: 0xFF, 5123: 0xFFFF, 5125: 0xFFFFFFFF}[ctype]
            bad = (indices >= count) | (indices == restart)
            if np.any(bad):
                k = int(np.nonzero(bad)[0][0])
                why = ("is the primitive restart value" if indices[k] == restart
                       else f"is not below the vertex count {count}")
                raise self.fail(f"index {k}: vertex {int(indices[k])} {why}", ip, "gltf.mesh.indices")
        else:
            indices = np.arange(count, dtype=np.int64)
        if mode == 4 and len(indices) % 3:
            raise self.fail(f"TRIANGLES with {len(indices)} vertices (not a multiple of 3)",
                            f"{where}/indices" if prim.indices is not None else where,
                            "gltf.mesh.indices")
        tris = triangles(mode, indices)
        targets = []
        for t, target in enumerate(prim.targets or []):
            target = target if isinstance(target, dict) else (vars(target) if target is not None else {})
            index = target.get("POSITION")
            if index is None:
                targets.append(np.zeros_like(points))
                continue
            tp = f"{where}/targets/{t}/POSITION"
            self._accessor_format(index, tp, "morph target POSITION", ("VEC3",),
                                  (5126, 5120, 5122) if self.quantized else (5126,))
            offsets = np.asarray(self.reader.read(index, tp), np.float64)
            if len(offsets) != count:
                raise self.fail(f"has {len(offsets)} elements, POSITION {count}", tp, "gltf.mesh.count")
            targets.append(offsets)
        return {"targets": targets, "points": points, "normals": normals, "tris": tris, "joints": joints,
                "weights": weights}

    def normalize_weights(self, weights: np.ndarray, joints: np.ndarray, m: int, p: int,
                          pointer: str) -> tuple[np.ndarray, np.ndarray]:
        """Renormalize one primitive's weights as engines do (spec: Meshes, "Weights").

        Weights whose float32 sum is within glTF-Validator's tolerance of one are kept as stored.
        Others are divided by their sum (one warning per primitive: how many vertices, the largest
        deviation of a sum from one and how far that moves a vertex at the bind pose); a vertex
        whose weights are all zero gets weight 1 on the joint of its ``JOINTS_0`` first component,
        as three.js's ``SkinnedMesh.normalizeSkinWeights`` does (another warning). With
        ``ReadOptions.strict_weights`` the first vertex off is an error instead.

        Args:
            weights: (V, K) non-negative float64 weights, every set concatenated.
            joints: (V, K) joint indices (in range wherever the weight is non-zero).
            m: Mesh index, for messages.
            p: Primitive index, for messages.
            pointer: JSON pointer of the primitive's attributes.

        Returns:
            (weights, joints), every row of weights summing to one.

        Raises:
            InputError: With strict weights, a vertex whose weights do not sum to one (gltf.skin.weights).
        """
        count = len(weights)
        # Sums as glTF-Validator computes them: float32 running sum, 2e-7 per non-zero weight.
        total = np.zeros(count, dtype=np.float32)
        for c in range(weights.shape[1]):
            total = (total + weights[:, c].astype(np.float32)).astype(np.float32)
        threshold = WEIGHT_SUM_TOLERANCE * np.count_nonzero(weights, axis=1)
        off = np.abs(total.astype(np.float64) - 1.0) > np.maximum(threshold, 1e-12)
        if not np.any(off):
            return weights, joints
        if getattr(self.options, "strict_weights", False):
            v = int(np.nonzero(off)[0][0])
            raise self.fail(f"vertex {v}: weights sum to {float(total[v]):.9g}, not 1 "
                            f"(tolerance {WEIGHT_SUM_TOLERANCE:g} per non-zero weight; "
                            "--strict-weights)", f"{pointer}/WEIGHTS_0", "gltf.skin.weights")
        sums = weights.sum(axis=1)
        zero = sums <= 0
        label = f"{self.mesh_label(m)} primitive {p}"
        if np.any(zero):
            weights = weights.copy()
            joints = joints.copy()
            first = int(np.nonzero(zero)[0][0])
            weights[zero] = 0.0
            weights[zero, 0] = 1.0
            self.warn(f"{label}: {int(zero.sum())} vertices have only zero weights (first: vertex "
                      f"{first}); each is bound with weight 1 to the joint of its JOINTS_0 first "
                      f"component (joint {int(joints[first, 0])} for vertex {first}), as three.js does")
            sums = np.where(zero, 1.0, sums)
        scaled = off & ~zero
        if np.any(scaled):
            deviation = np.abs(sums - 1.0)
            worst = int(np.argmax(np.where(scaled, deviation, -1.0)))
            points = self._current_points
            moved = float(np.max(np.where(scaled, deviation * np.linalg.norm(points, axis=1), 0.0)))
            self.warn(f"{label}: weights of {int(scaled.sum())} vertices do not sum to 1 (largest "
                      f"deviation {deviation[worst]:.3g}: vertex {worst} sums to {sums[worst]:.9g}); "
                      f"renormalized, as engines do (at the bind pose that moves a vertex by up to "
                      f"{moved:.3g} scene units; --strict-weights refuses such files)")
            self.renormalized[(m, p)] = (weights.copy(), joints.copy())
        weights = weights / sums[:, None]
        return weights, joints

    # -- skins -----------------------------------------------------------------------------------

    def read_skin(self, s: int) -> tuple[list, np.ndarray]:
        """Check skin ``s``; return its joint node indices and (J, 4, 4) inverse bind matrices."""
        skin = self.gltf.skins[s]
        where = f"/skins/{s}"
        joints = skin.joints
        if not isinstance(joints, list) or not joints:
            raise self.fail("skin has no joints", f"{where}/joints", "gltf.skin.joints")
        seen: dict[int, int] = {}
        for k, j in enumerate(joints):
            require_index(j, len(self.gltf.nodes), f"{where}/joints/{k}", self.file, "node")
            if j in seen:
                raise self.fail(f"node {j} is listed twice (joints {seen[j]} and {k})",
                                f"{where}/joints/{k}", "gltf.skin.joints")
            seen[j] = k
        if skin.skeleton is not None:
            root = require_index(skin.skeleton, len(self.gltf.nodes), f"{where}/skeleton",
                                 self.file, "node")
            for k, j in enumerate(joints):
                node = j
                while node != -1 and node != root:
                    node = self.parent[node]
                if node == -1:
                    raise self.fail(f"skeleton node {root} is not an ancestor of joint {k} "
                                    f"({self.node_label(j)})", f"{where}/skeleton",
                                    "gltf.skin.skeleton")
        count = len(joints)
        if skin.inverseBindMatrices is None:
            ibm = np.broadcast_to(np.eye(4), (count, 4, 4))
        else:
            pointer = f"{where}/inverseBindMatrices"
            self._accessor_format(skin.inverseBindMatrices, pointer, "inverseBindMatrices",
                                  ("MAT4",), (5126,), code="gltf.skin.ibm")
            ibm = self.reader.read(skin.inverseBindMatrices, pointer)
            if len(ibm) < count:
                raise self.fail(f"accessor {skin.inverseBindMatrices} holds {len(ibm)} inverse bind "
                                f"matrices for {count} joints", pointer, "gltf.skin.ibm")
            ibm = np.array(ibm[:count], dtype=np.float64)
            bad = ~np.all(np.isclose(ibm[:, 3], (0.0, 0.0, 0.0, 1.0), atol=1e-5), axis=1)
            if np.any(bad):
                k = int(np.nonzero(bad)[0][0])
                raise self.fail(f"inverse bind matrix {k} is not affine (last row "
                                f"{ibm[k, 3].tolist()})", pointer, "gltf.skin.ibm")
            ibm[:, 3] = (0.0, 0.0, 0.0, 1.0)
        return list(joints), np.array(ibm)

    # -- assembly --------------------------------------------------------------------------------

    def select(self, values: tuple, names: list, what: str) -> list:
        """Indices selected by ReadOptions values (names or decimal indices); all when empty."""
        if not values:
            return list(range(len(names)))
        chosen = []
        for value in values:
            text = str(value)
            hits = [i for i, name in enumerate(names) if name == text]
            if not hits and text.isdigit() and int(text) < len(names):
                hits = [int(text)]
            if not hits:
                known = ", ".join(repr(n) if n else str(i) for i, n in enumerate(names)) or "none"
                raise OptionsError(f"no {what} named {text!r} (known: {known})", file=self.file,
                                   location=f"/{what}s", code="gltf.option")
            chosen.extend(h for h in hits if h not in chosen)
        return sorted(chosen)

    def run(self, stem: str) -> SourceScene:
        gltf = self.gltf
        self.read_nodes()
        animations = self.read_animations()
        skin_names = [s.name if isinstance(s.name, str) else "" for s in gltf.skins]
        anim_names = [a.name if isinstance(a.name, str) else "" for a in gltf.animations]
        skins = self.select(self.options.skeletons, skin_names, "skin")
        chosen_anims = self.select(self.options.clips, anim_names, "animation")
        time_range = check_time_range(self.options, self.file)
        if time_range is not None:
            lo, hi = time_range

        # Scene and root prim name.
        scene_index = gltf.scene
        if scene_index is not None:
            require_index(scene_index, len(gltf.scenes), "/scene", self.file, "scene")
        elif gltf.scenes:
            scene_index = 0
        scene_name = gltf.scenes[scene_index].name if scene_index is not None else None
        root = make_identifier(scene_name if isinstance(scene_name, str) and scene_name else stem,
                               "Scene")
        names = NameAllocator()

        # Skinned nodes, in node order; mesh nodes without a skin are attachment candidates.
        users: dict[int, list] = {}
        unskinned = []
        for i, node in enumerate(gltf.nodes):
            if node.mesh is not None and node.skin is None:
                unskinned.append(i)
            elif node.skin is not None and node.mesh is None:
                self.warn(f"{self.node_label(i)} has a skin but no mesh; ignored")
            elif node.skin is not None:
                users.setdefault(node.skin, []).append(i)
                if node.skin in skins and not np.allclose(self.rest_world(i), np.eye(4), atol=1e-9):
                    self.warn(f"{self.node_label(i)}: the skinned mesh node's transform is not "
                              "identity; it is ignored, as glTF 2.0 requires (joint transforms "
                              "place the mesh)")

        attachments = self.plan_attachments(unskinned, skins, set(users),
                                            [animations[a] for a in chosen_anims])
        converted = [s for s in skins if s in users or s in attachments]
        for s in skins:
            if s not in converted:
                self.warn(f"skin {s} (/skins/{s}) is used by no mesh node; left out")
        if VIRTUAL_SKIN in attachments:
            converted.append(VIRTUAL_SKIN)
        if not converted:
            why = ("the file has no skins and no animation moves a mesh" if not gltf.skins
                   else "no skin is used by a mesh node and no animation moves a mesh")
            if any(animations[a].weight_channels for a in chosen_anims):
                why += " (its animations move only morph target weights, which Virtual Bones cannot hold)"
            raise UnsupportedError(f"{why}; Virtual Bones bakes skinned or animated meshes",
                                   file=self.file, location="/skins", code="gltf.noSkin")

        result = []
        anim_prim_names = {}
        for s in converted:
            base = "Nodes" if s == VIRTUAL_SKIN else make_identifier(gltf.skins[s].name, f"skin{s}")
            anim_prim_names[s] = names.take(f"{base}_Anim")
        mesh_names = {}
        for s in anim_prim_names:
            nodes = list(users.get(s, [])) + [a.node for a in attachments.get(s, [])]
            for node in nodes:
                mesh = gltf.nodes[node].mesh
                base = make_identifier(gltf.nodes[node].name or gltf.meshes[mesh].name, f"node{node}")
                prims = gltf.meshes[mesh].primitives or []
                if not isinstance(prims, list) or not prims:
                    raise self.fail("mesh has no primitives", f"/meshes/{mesh}/primitives",
                                    "gltf.mesh.attribute")
                for p in range(len(prims)):
                    mesh_names[(node, p)] = names.take(base if len(prims) == 1 else f"{base}_p{p}")

        lod_of_node, lod_sizes = self.read_lods(users)
        raw_weights = []
        for s, anim_name in anim_prim_names.items():
            joints, ibm = self.read_skin(s) if s != VIRTUAL_SKIN else ([], np.zeros((0, 4, 4)))
            bone_names = NameAllocator()
            bones = [bone_names.take(make_identifier(gltf.nodes[j].name, f"node{j}")) for j in joints]
            bone_nodes = list(joints)
            ibms = list(ibm)
            meshes, raws, morphs = [], [], []

            def add_mesh(node, m, p, data, indices, weights, rigid):
                level = lod_of_node.get(node, (None, 0))
                meshes.append(SkinnedMesh(
                    path=f"/{root}/{mesh_names[(node, p)]}",
                    points=data["points"],
                    face_vertex_counts=np.full(len(data["tris"]), 3, dtype=np.int32),
                    face_vertex_indices=data["tris"].reshape(-1).astype(np.int32),
                    bone_indices=indices.astype(np.int32),
                    bone_weights=weights,
                    normals=data["normals"],
                    normals_interpolation="vertex",
                    source_path=f"/nodes/{node} /meshes/{m}/primitives/{p}",
                    lod=level[1] if level[0] in users.get(s, []) else 0))
                raws.append(None if rigid else self.renormalized.get((m, p)))
                morphs.append((node, m, p, data["targets"]))

            for node in users.get(s, []):
                m = gltf.nodes[node].mesh
                for p in range(len(gltf.meshes[m].primitives)):
                    data = self.read_primitive(m, p, len(joints), s)
                    add_mesh(node, m, p, data, data["joints"], data["weights"], False)
            for attachment in attachments.get(s, []):
                if attachment.bone in bone_nodes[:len(joints)]:
                    bone = bone_nodes.index(attachment.bone)
                elif attachment.bone in bone_nodes:
                    bone = bone_nodes.index(attachment.bone)
                else:
                    bone = len(bone_nodes)
                    bone_nodes.append(attachment.bone)
                    ibms.append(np.eye(4))
                    bones.append(bone_names.take(make_identifier(gltf.nodes[attachment.bone].name,
                                                                 f"node{attachment.bone}")))
                node = attachment.node
                m = gltf.nodes[node].mesh
                place = self.attachment_matrix(attachment, ibms[bone])
                for p in range(len(gltf.meshes[m].primitives)):
                    try:
                        data = self.read_primitive(m, p, len(joints), s, rigid=True)
                    except UnsupportedError as error:
                        if error.code != "gltf.mesh.mode":
                            raise
                        # Points and lines attached to a bone: Virtual Bones binds triangles only.
                        self.warn(f"{self.node_label(node)} primitive {p}: {error.message}; left out")
                        continue
                    data["points"] = data["points"] @ place[:3, :3].T + place[:3, 3]
                    if data["normals"] is not None:
                        normals = data["normals"] @ np.linalg.inv(place[:3, :3])
                        lengths = np.linalg.norm(normals, axis=1, keepdims=True)
                        data["normals"] = np.divide(normals, lengths, out=np.zeros_like(normals),
                                                    where=lengths > 0)
                    data["targets"] = [t @ place[:3, :3].T for t in data["targets"]]
                    count = len(data["points"])
                    add_mesh(node, m, p, data, np.full((count, 1), bone), np.ones((count, 1)), True)
            ibm_all = np.array(ibms)
            relevant = self.ancestors_and_self(bone_nodes)
            relevant_set = set(relevant)
            clips = []
            clip_names = NameAllocator()
            moved = False   # some selected animation moves the skin (maybe outside the time range)
            for a in chosen_anims:
                anim = animations[a]
                channels = [c for c in anim.channels if c.node in relevant_set]
                if not channels:
                    continue
                moved = True
                start, end = anim.start, anim.end
                if time_range is not None:
                    start, end = max(start, lo), min(end, hi)
                    if end < start:
                        self.warn(f"/animations/{a}: outside the chosen time range; left out")
                        continue
                clip = self.make_clip(clip_names.take(anim.name), start, end, channels,
                                      bone_nodes, relevant, ibm_all)
                clips.append(clip)
                self._clip_sources[id(clip)] = anim
            if not clips:
                if time_range is not None and moved and not any(_overlaps(animations[a], lo, hi) for a in chosen_anims):
                    # No animation reaches into the range: the bake would be a held pose only.
                    spans = [(animations[a].start, animations[a].end) for a in chosen_anims]
                    first, last = min(p[0] for p in spans), max(p[1] for p in spans)
                    raise OptionsError(f"the frame range {lo:g}..{hi:g} s lies outside the animations' "
                                       f"time range {first:g}..{last:g} s", file=self.file,
                                       location="/animations", code="gltf.option")
                why = ("the animations that move its joints lie outside the chosen time range"
                       if moved else "no animation moves its joints")
                self.warn(f"skin {s} (/skins/{s}): {why}; a one-row rest clip is written")
                t0 = 0.0 if time_range is None else float(lo)
                clips.append(self.make_clip(clip_names.take("rest"), t0, t0, [], bone_nodes,
                                            relevant, ibm_all))
            for node, m, p, targets in morphs:
                if targets:
                    self.measure_morph(node, m, p, targets, clips)
            leveled = [lod_of_node[n][0] for n in users.get(s, []) if lod_of_node.get(n, (None, 0))[1] > 0
                       and lod_of_node[n][0] in users.get(s, [])]
            result.append(SkinnedAnimation(name=anim_name, path=f"/{root}/{anim_name}", bones=tuple(bones),
                                           clips=tuple(clips), meshes=tuple(meshes),
                                           source=self.file, bind_transforms=bind_transforms(ibm_all),
                                           lod_screen_sizes=lod_sizes.get(leveled[0]) if leveled else None,
                                           bone_parents=self.bone_parents(bone_nodes)))
            raw_weights.append(tuple(raws))
        if not result:
            raise UnsupportedError("no skin is used by a mesh node; nothing to bake",
                                   file=self.file, location="/skins", code="gltf.noSkin")
        return GltfScene(animations=tuple(result), up_axis="Y", meters_per_unit=1.0,
                         time_codes_per_second=TIME_CODES_PER_SECOND, default_prim=root,
                         warnings=tuple(self.warnings), source=self.file,
                         raw_weights=tuple(raw_weights))

    def read_lods(self, users: dict) -> tuple:
        """Levels of detail from ``MSFT_lod`` on skinned nodes (spec/virtual-bones.md 20.3).

        Returns ``({node: (LOD 0 node, level)}, {LOD 0 node: screen sizes or None})``: a node with
        ``extensions.MSFT_lod.ids`` is level 0 and its ids are levels 1, 2, ...; its
        ``extras.MSFT_screencoverage`` (one value per level) gives the thresholds, its last entry
        (where LOD n-1 ends) dropped. A level node bound to another skin than its LOD 0 is left at
        level 0 of its own skin, with a warning.
        """
        levels, sizes = {}, {}
        skin_of = {node: s for s, nodes in users.items() for node in nodes}
        for i, node in enumerate(self.gltf.nodes):
            lod = (node.extensions or {}).get("MSFT_lod") if isinstance(node.extensions, dict) else None
            if not isinstance(lod, dict) or i not in skin_of:
                continue
            ids = lod.get("ids")
            if not isinstance(ids, list) or not all(isinstance(k, int) and 0 <= k < len(self.gltf.nodes) for k in ids):
                raise self.fail("MSFT_lod ids must be node indices", f"/nodes/{i}/extensions/MSFT_lod/ids",
                                "gltf.index")
            levels[i] = (i, 0)
            for level, k in enumerate(ids, start=1):
                if skin_of.get(k) != skin_of[i]:
                    self.warn(f"{self.node_label(i)}: MSFT_lod level {level} ({self.node_label(k)}) is not "
                              "skinned with the same skin; it is not a level of this character")
                    continue
                levels[k] = (i, level)
            coverage = (node.extras or {}).get("MSFT_screencoverage") if isinstance(node.extras, dict) else None
            ok = isinstance(coverage, list) and len(coverage) >= len(ids) and \
                all(isinstance(c, (int, float)) and not isinstance(c, bool) for c in coverage)
            sizes[i] = tuple(float(c) for c in coverage[:len(ids)]) if ok else None
        return levels, sizes

    def plan_attachments(self, unskinned: list, skins: list, used: set, chosen: list) -> dict:
        """Which skin, and which bone of it, every mesh node without a skin follows.

        Rule (spec: Rigid attachments): a mesh node whose ancestor (or itself) is a joint of a
        selected skin follows the nearest such joint ``J`` (of the lowest-index selected skin
        listing it; that skin is converted even when no skinned mesh uses it), unless a node between
        ``J`` (exclusive) and the mesh node (inclusive) is animated by a selected animation: then it
        follows the deepest such node, which becomes an extra bone of that skin (bone matrix: its
        world transform). A mesh node under no joint that an animated node moves follows the
        deepest animated node as an extra bone of the first converted skin, or, when no skin is
        converted, of an animation of its own (:data:`VIRTUAL_SKIN`); a mesh node in the default
        scene that nothing moves follows the root of its tree, fixed, as an extra bone of the first
        converted skin (when there is one). Every case but the joint one is warned about.

        Args:
            unskinned: Mesh nodes without a skin, in node order.
            skins: Selected skin indices, ascending.
            used: Skins used by a skinned mesh node.
            chosen: The selected animations (_Animation records).

        Returns:
            ``{skin: [_Attachment, ...]}``: mesh nodes under joints in node order, then the others
            (moved ones first); the key :data:`VIRTUAL_SKIN` holds the attachments of an animation
            without a skin.
        """
        animated = {c.node for anim in chosen for c in anim.channels}
        joint_skin: dict[int, int] = {}
        for s in skins:
            for j in self.read_skin(s)[0]:
                joint_skin.setdefault(j, s)
        result: dict[int, list] = {}
        pending = []   # (node, path, moving) of mesh nodes under no joint
        for n in unskinned:
            path, node = [], n
            while node != -1 and node not in joint_skin:
                path.append(node)
                node = self.parent[node]
            moving = [x for x in path if x in animated]   # deepest first
            if node == -1:
                pending.append((n, path, moving))
                continue
            bone = moving[0] if moving else node
            self._attach(result, joint_skin[node], n, bone, path)
        converted = [s for s in skins if s in used or s in result]
        pending.sort(key=lambda item: not item[2])   # moved ones first: they may make the virtual skin
        for n, path, moving in pending:
            if moving:
                skin = converted[0] if converted else VIRTUAL_SKIN
                target = f"skin {skin}" if converted else "an animation of its own (the file converts no skin)"
                self.warn(f"{self.node_label(n)} has a mesh but no skin and follows the animated "
                          f"{self.node_label(moving[0])}, which is under no joint of a converted skin; it "
                          f"is attached to {target} as an extra bone")
                self._attach(result, skin, n, moving[0], path)
            elif converted and self.in_scene(n):
                self.warn(f"{self.node_label(n)} has a mesh but no skin, and neither a joint nor an "
                          f"animation moves it; it is attached to skin {converted[0]} as an extra bone "
                          "fixed where its node puts it (as engines show it)")
                self._attach(result, converted[0], n, path[-1], path)
            elif self.in_scene(n) and VIRTUAL_SKIN in result:
                self.warn(f"{self.node_label(n)} has a mesh but no skin, and nothing moves it; it is "
                          "attached to the animation of the file's animated meshes as a fixed extra bone")
                self._attach(result, VIRTUAL_SKIN, n, path[-1], path)
            else:
                self.warn(f"{self.node_label(n)} has a mesh but no skin, nothing moves it and "
                          f"{'it is not in the default scene' if converted else 'the file converts no skin'}; "
                          "left out")
        return result

    def _attach(self, result: dict, skin: int, node: int, bone: int, path: list) -> None:
        """Record that ``node`` follows ``bone`` (an ancestor-or-self on ``path``, or the joint above
        it) with the constant rest transform between them."""
        below = path[:path.index(bone)] if bone in path else path   # bone (exclusive) .. node
        rel = np.eye(4)
        for x in reversed(below):
            rel = rel @ self.rest_local[x]
        result.setdefault(skin, []).append(_Attachment(node, bone, rel))

    def in_scene(self, node: int) -> bool:
        """Whether ``node`` is in the default scene (``scene``, else ``scenes[0]``; every node when
        the file has no scenes)."""
        if not self.gltf.scenes:
            return True
        index = self.gltf.scene if self.gltf.scene is not None else 0
        while self.parent[node] != -1:
            node = self.parent[node]
        return node in (self.gltf.scenes[index].nodes or [])

    def attachment_matrix(self, attachment: _Attachment, ibm: np.ndarray) -> np.ndarray:
        """``inverse(IBM_bone) · rel``: takes the mesh node's POSITION into the bind space of its
        bone, so that ``M_bone(t) · result = W_node(t)`` (spec: Rigid attachments).

        Raises:
            InputError: The bone's inverse bind matrix is singular (gltf.skin.ibm).
        """
        if abs(np.linalg.det(ibm[:3, :3])) < 1e-12:
            raise self.fail(f"the inverse bind matrix of {self.node_label(attachment.bone)} is singular, "
                            f"so {self.node_label(attachment.node)} cannot be attached to it",
                            f"/nodes/{attachment.node}", "gltf.skin.ibm")
        return np.linalg.inv(ibm) @ attachment.rel

    def measure_morph(self, node: int, m: int, p: int, targets: list, clips: list) -> None:
        """Warn that a primitive's morph targets are dropped, with the largest displacement they
        cause over the converted clips (spec: Meshes, "Morph targets")."""
        offsets = np.stack(targets)                       # (T, V, 3)
        count = offsets.shape[0]
        defaults = (getattr(self.gltf.nodes[node], "weights", None) or getattr(self.gltf.meshes[m], "weights", None)
                    or [])
        defaults = np.resize(np.asarray(defaults, dtype=np.float64), count) if len(defaults) else \
            np.zeros(count)
        worst = (0.0, 0, "", 0.0)
        for clip in clips:
            anim = self._clip_sources.get(id(clip))
            channel = anim.weight_channels.get(node) if anim is not None else None
            if channel is None:
                times, weights = np.array([clip.start_time]), defaults[None, :]
            else:
                keys = channel.keys
                inside = keys[(keys >= clip.start_time) & (keys <= clip.end_time)]
                times = np.unique(np.concatenate([inside, [clip.start_time, clip.end_time]]))
                if channel.interpolation == "CUBICSPLINE" and len(times) > 1:
                    steps = np.linspace(0.0, 1.0, 9)[1:-1]
                    times = np.unique(np.concatenate(
                        [times, (times[:-1, None] + np.diff(times)[:, None] * steps).reshape(-1)]))
                weights = sample_channel(times, keys, channel.values, channel.interpolation, False)
                if weights.shape[1] != count:
                    continue
            chunk = max(1, int(4_000_000 // max(1, offsets.shape[1] * count)))
            for start in range(0, len(times), chunk):
                part = slice(start, start + chunk)
                lengths = np.linalg.norm(np.einsum("nt,tvc->nvc", weights[part], offsets), axis=2)
                row, vertex = np.unravel_index(int(np.argmax(lengths)), lengths.shape)
                if lengths[row, vertex] > worst[0]:
                    worst = (float(lengths[row, vertex]), int(vertex), clip.name,
                             float(times[part][row]))
        label = f"{self.mesh_label(m)} primitive {p} of {self.node_label(node)}"
        rest = "the rest shape used is POSITION as stored (every target weight 0)"
        if worst[0] > 0:
            self.warn(f"{label}: {count} morph targets are not baked; {rest}; over the converted "
                      f"clips the dropped targets move a vertex by up to {worst[0]:.4g} scene units "
                      f"(vertex {worst[1]}, clip '{worst[2]}' at {worst[3]:.4g} s)")
        else:
            self.warn(f"{label}: {count} morph targets are not baked; {rest}; their weights stay 0 "
                      "over the converted clips, so nothing is lost")

    def make_clip(self, name: str, start: float, end: float, channels: list, joints: list,
                  relevant: list, ibm: np.ndarray) -> AnimationClip:
        """An AnimationClip whose sample() evaluates the node hierarchy at any times."""
        by_node: dict[int, dict] = {}
        for channel in channels:
            by_node.setdefault(channel.node, {})[channel.path] = channel
        parent = self.parent
        rest_local = self.rest_local
        rest_trs = self.rest_trs
        joint_count = len(joints)

        def sample(times) -> np.ndarray:
            times = np.asarray(times, dtype=np.float64).reshape(-1)
            n = len(times)
            world: dict[int, np.ndarray] = {}
            for node in relevant:
                if node in by_node:
                    t, r, s = rest_trs[node]
                    animated = by_node[node]
                    values = {}
                    for key, rest in (("translation", t), ("rotation", r), ("scale", s)):
                        ch = animated.get(key)
                        values[key] = (rest[None, :] if ch is None else
                                       sample_channel(times, ch.keys, ch.values, ch.interpolation,
                                                      key == "rotation"))
                    local = compose_trs(values["translation"], values["rotation"], values["scale"])
                    local = np.broadcast_to(local, (n, 4, 4))
                else:
                    local = rest_local[node]
                p = parent[node]
                world[node] = local if p == -1 else world[p] @ local
            out = np.empty((n, joint_count, 4, 4))
            for k, j in enumerate(joints):
                out[:, k] = world[j] @ ibm[k]
            return out

        keys = np.unique(np.concatenate([c.keys for c in channels])) if channels else np.array([start])
        keys = keys[(keys >= start) & (keys <= end)]
        return AnimationClip(name=name, start_time=float(start), end_time=float(end), sample=sample,
                             native_rate=native_rate(keys), loop=None, key_times=keys)


def native_rate(keys: np.ndarray) -> float:
    """Rows per second proposed for a clip: the key rate when keys sit on a regular grid.

    When every key time lies within 0.1% of a step on a grid of spacing ``dt`` (the smallest gap
    between keys) and ``1/dt`` is between 10 and 240 Hz, the rate is ``1/dt`` (rounded to an integer
    when within 0.1% of one); otherwise :data:`DEFAULT_RATE`.

    Args:
        keys: Sorted unique key times of the clip's channels, seconds.
    """
    if len(keys) < 2:
        return DEFAULT_RATE
    dt = float(np.min(np.diff(keys)))
    if dt <= 0:
        return DEFAULT_RATE
    steps = (keys - keys[0]) / dt
    if np.max(np.abs(steps - np.round(steps))) > 1e-3:
        return DEFAULT_RATE
    rate = 1.0 / dt
    if not 10.0 <= rate <= 240.0:
        return DEFAULT_RATE
    if abs(rate - round(rate)) <= 1e-3 * rate:
        rate = float(round(rate))
    return rate


def sniff(path) -> bool:
    """Whether a file looks like glTF: GLB magic, or JSON whose first 64 KiB mention ``"asset"``.

    Used by the converter registry when a file's suffix is not conclusive. Never raises.
    """
    try:
        with open(path, "rb") as stream:
            head = stream.read(1 << 16)
    except OSError:
        return False
    if head[:4] == GLB_MAGIC:
        return True
    text = head.lstrip(b"\xef\xbb\xbf \t\r\n")
    return text[:1] == b"{" and b'"asset"' in text


def _overlaps(animation, lo: float, hi: float) -> bool:
    """Whether an animation's key time range meets ``[lo, hi]``."""
    return animation.start <= hi and animation.end >= lo


def check_time_range(options: ReadOptions, file: str) -> tuple[float, float] | None:
    """The options' time range as two finite seconds ``lo <= hi``, or None.

    Raises:
        OptionsError: When it is not two finite numbers in order.
    """
    time_range = options.time_range
    if time_range is None:
        return None
    try:
        lo, hi = (float(x) for x in time_range)
    except (TypeError, ValueError):
        raise OptionsError(f"time range {time_range!r} is not two numbers (seconds)", file=file,
                           code="gltf.option") from None
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
        raise OptionsError(f"time range {time_range!r} is empty or not finite", file=file,
                           code="gltf.option")
    return lo, hi


def read(path, options: ReadOptions | None = None) -> SourceScene:
    """Read a .gltf or .glb file into skinned animations (one per skin).

    Args:
        path: The glTF file.
        options: Selection of skins (names or indices) and animations, time range (seconds), and
            whether buffer URIs may leave the asset's folder.

    Returns:
        The scene: Y up, metres, 24 time codes per second, one SkinnedAnimation per selected skin
        used by a mesh node, warnings (morph targets, ignored skinned-node transforms, ...).

    Raises:
        InputError: Malformed, inconsistent or unsafe input (one line, with a JSON pointer).
        UnsupportedError: Content vbusd cannot bake (no skins, line or point primitives, ...).
        OptionsError: Selections that name nothing in the file.
    """
    options = options or ReadOptions()
    check_time_range(options, str(path))      # options are checked before any work starts
    gltf, buffers = load(path, options)
    converter = _Converter(gltf, buffers, str(path), options)
    return converter.run(Path(path).stem)


def bind_transforms(inverse_binds: np.ndarray):
    """The joints' bind transforms ``B = inverse(inverseBindMatrix)`` (format 1.1 sockets), or None.

    The skinning matrices are ``jointWorld @ inverseBind`` in the scene root's space, so
    ``jointWorld = M @ B``: the glTF node's world matrix that a socket returns
    (spec/gltf-conversion.md, "Sockets"). None when an inverse bind matrix is singular.
    """
    inverse_binds = np.asarray(inverse_binds, dtype=np.float64)
    if inverse_binds.size == 0 or np.any(np.abs(np.linalg.det(inverse_binds[:, :3, :3])) < 1e-12):
        return None
    return np.linalg.inv(inverse_binds)
