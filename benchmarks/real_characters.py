"""Real characters convert whole (issue 12): every shared asset, what an engine shows and what converts.

For every glTF and UsdSkel asset under ``../shared/assets`` the script lists the meshes an engine
shows, converts the asset with the default options (weights renormalized, rigid attachments,
``--on-bad-clip error``), and says which of those meshes became bound meshes (skinned, or rigid:
glTF mesh nodes under joints, UsdSkel constant bindings and tessellated implicit gprims), which
did not and why, and how far the decoded result lies from an independent one:

* glTF: **three.js** r187 under Node (``tests/node/skin_pose.mjs``: GLTFLoader, AnimationMixer,
  SkinnedMesh CPU skinning, scene-graph world matrices). "Shown" = every mesh of three.js's scene,
  keyed by glTF node and primitive. The asset is baked in affineMatrix/float32 and decoded by the
  reference decoder at up to ``--rows`` rows per clip spread evenly; three.js is posed at the same
  times.
* UsdSkel: UsdSkel's own ``SkinningQuery.ComputeSkinnedPoints`` (``vbusd convert``'s accuracy
  report, ``--check-rows``). "Shown" = every visible ``Gprim`` of the stage whose purpose is not
  ``guide``.

Errors are the largest distance over the diagonal of the reference's bounding box (per mesh, the
worst mesh of the asset).

Run: ``python benchmarks/real_characters.py`` (the markdown table of docs/converters/
real-characters.md) or ``--format json``; ``--assets DIR`` (default ``../shared/assets``) and
``--rows N`` (default 48). "Rigid attachments" counts glTF mesh nodes without a skin and UsdSkel
prims deformed rigidly (constant influences, own or inherited; tessellated implicit gprims) or
placed by their own transform (meshes no binding reaches).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ASSETS = REPO.parent / "shared" / "assets"
NODE_SCRIPT = REPO / "tests" / "node" / "skin_pose.mjs"


def _three(path: Path, clip: str, times) -> dict:
    result = subprocess.run(["node", str(NODE_SCRIPT), str(path), clip, *[f"{t:.17g}" for t in times]],
                            cwd=NODE_SCRIPT.parent, capture_output=True, text=True, timeout=600)
    if result.returncode != 0:
        raise RuntimeError(result.stderr[-2000:])
    return json.loads(result.stdout)


def _rows(count: int, limit: int) -> np.ndarray:
    if count <= limit:
        return np.arange(count)
    return np.unique(np.round(np.linspace(0, count - 1, limit)).astype(np.int64))


def gltf_entry(path: Path, limit: int) -> dict:
    """Convert one glTF asset and compare every converted mesh with three.js."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.converters import gltf
    from vbusd.decoders.reference import skin_mesh
    from vbusd.format.errors import VbusdError
    from vbusd.io.gltf import load

    start = time.perf_counter()
    shown = set(_three(path, "-", [0.0])["poses"][0]["byNode"])
    entry = {"asset": f"gltf/{path.parent.name}/{path.name}", "shown": len(shown)}
    try:
        scene = gltf.read(path)
    except VbusdError as error:
        entry.update(refused=str(error), converted=0, attachments=0, dropped=sorted(shown))
        return entry
    document, _ = load(path)
    names = [gltf.make_identifier(a.name, f"animation{i}") for i, a in enumerate(document.animations)]
    converted, attachments, skinned = {}, 0, 0
    for ai, animation in enumerate(scene.animations):
        for mi, mesh in enumerate(animation.meshes):
            node = int(mesh.source_path.split()[0].split("/")[2])
            primitive = int(mesh.source_path.rsplit("/", 1)[1])
            converted[f"{node}:{primitive}"] = (ai, mi)
            if document.nodes[node].skin is None:
                attachments += 1
            else:
                skinned += 1
    entry.update(converted=len(converted), skinned=skinned, attachments=attachments,
                 dropped=sorted(shown - set(converted)), warnings=list(scene.warnings),
                 clips=sorted({c.name for a in scene.animations for c in a.clips}))
    baked = [bake(a, BakeOptions(encoding="affineMatrix", texel_format="float32")) for a in scene.animations]
    # One three.js run per glTF animation, at the rows of every skin's clip of it.
    plans: dict = {}
    for ai, vb in enumerate(baked):
        for ci, clip in enumerate(vb.clips):
            rows = _rows(clip.row_count, limit)
            times = clip.start_time + rows / clip.rows_per_second
            key = f"#{names.index(clip.name)}" if clip.name in names else "-"
            plans.setdefault(key, []).append((ai, ci, rows, times))
    worst = 0.0
    for key, items in plans.items():
        all_times = sorted({float(t) for _, _, _, times in items for t in times})
        poses = _three(path, key, all_times)["poses"]
        at = {round(p["time"], 12): p["byNode"] for p in poses}
        for ai, ci, rows, times in items:
            vb = baked[ai]
            for node_key, (a, mi) in converted.items():
                if a != ai:
                    continue
                ours, _ = skin_mesh(vb, vb.meshes[mi], ci, rows / vb.clips[ci].rows_per_second)
                theirs = np.array([np.reshape(at[round(float(t), 12)][node_key], (-1, 3)) for t in times])
                flat = theirs.reshape(-1, 3)
                diagonal = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0))) or 1.0
                worst = max(worst, float(np.linalg.norm(ours - theirs, axis=-1).max()) / diagonal)
    entry.update(max_error=worst, reference="three.js r187", seconds=round(time.perf_counter() - start, 2))
    return entry


def _shown_gprims(path: Path) -> dict:
    """Visible, non-guide Gprims of a stage: {path: type name}."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    shown = {}
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Gprim):
            continue
        imageable = UsdGeom.Imageable(prim)
        if imageable.ComputeVisibility() == UsdGeom.Tokens.invisible or \
                imageable.ComputePurpose() == UsdGeom.Tokens.guide:
            continue
        shown[str(prim.GetPath())] = prim.GetTypeName()
    return shown


def usd_entry(path: Path, root: Path, limit: int) -> dict:
    """Convert one UsdSkel asset with vbusd convert's accuracy report (UsdSkel's own skinning)."""
    import vbusd  # noqa: F401  (schema)
    from vbusd.jobs.conversion import ConvertOptions, convert
    from vbusd.format.errors import VbusdError

    start = time.perf_counter()
    shown = _shown_gprims(path)
    entry = {"asset": str(path.relative_to(root)), "shown": len(shown)}
    with tempfile.TemporaryDirectory() as folder:
        try:
            report = convert(path, Path(folder) / "out.usda",
                             ConvertOptions(texel_format="float32", check_rows=limit))
        except VbusdError as error:
            entry.update(refused=f"{error.code}: {error.message}", converted=0, attachments=0,
                         dropped=sorted(shown))
            return entry
    meshes = [m for a in report.animations for m in a.meshes]
    converted = {m.path for m in meshes}
    loose = {w.split(":")[0] for w in report.warnings if "no skeleton binding reaches it" in w}
    rigid = sum(1 for m in meshes if m.path in loose or _is_rigid(path, m.path))
    dropped = sorted(set(shown) - converted)
    entry.update(converted=len(converted), attachments=rigid, skinned=len(converted) - rigid,
                 dropped=[f"{p} ({shown[p]}: {_why(p, report.warnings)})" for p in dropped],
                 warnings=list(report.warnings), clips=sorted({c.name for a in report.animations for c in a.clips}),
                 max_error=max((m.max_error_fraction or 0.0) for m in meshes),
                 reference="UsdSkel ComputeSkinnedPoints", seconds=round(time.perf_counter() - start, 2))
    return entry


def _is_rigid(path: Path, prim_path: str) -> bool:
    """Whether UsdSkel deforms the prim rigidly (constant influences, own or inherited)."""
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    prim = stage.GetPrimAtPath(prim_path)
    node = prim
    while node and not node.IsA(UsdSkel.Root):
        node = node.GetParent()
    if not node:
        return False
    root = UsdSkel.Root(node)
    cache.Populate(root, Usd.PrimDefaultPredicate)
    for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
        for target in binding.GetSkinningTargets():
            if str(target.GetPrim().GetPath()) == prim_path:
                return bool(target.IsRigidlyDeformed())
    return False


def _why(prim_path: str, warnings: list) -> str:
    for warning in warnings:
        if warning.startswith(prim_path + ":"):
            return warning[len(prim_path) + 2:].split(";")[0].split(" (")[0]
    return "not bound to a skeleton: UsdSkel does not move it"


def survey(root: Path, limit: int) -> list:
    """One entry per asset under ``root`` (gltf/*/*.gl*, usdskel/**/*.usd*)."""
    entries = [gltf_entry(p, limit) for p in sorted((root / "gltf").glob("*/*.gl*"))]
    usd = sorted(p for p in (root / "usdskel").rglob("*") if p.suffix.lower() in (".usda", ".usdc", ".usdz", ".usd"))
    entries += [usd_entry(p, root, limit) for p in usd]
    return entries


def markdown(entries: list) -> str:
    """The table of docs/converters/real-characters.md."""
    lines = ["| asset | meshes shown | converted (skinned + rigid) | rigid attachments | not converted (why) | "
             "max error (of bbox diagonal) | against |",
             "|---|--:|--:|--:|---|--:|---|"]
    for e in entries:
        if "refused" in e:
            why = e["refused"].split(": ", 1)[-1] if e["refused"].startswith(("/", ".")) else e["refused"]
            lines.append(f"| {e['asset']} | {e['shown']} | refused | | {why.replace('|', '/')} | | |")
            continue
        dropped = "<br>".join(d.replace("|", "/") for d in e["dropped"]) or "—"
        lines.append(f"| {e['asset']} | {e['shown']} | {e['converted']} | {e['attachments']} | {dropped} | "
                     f"{e['max_error']:.2g} | {e['reference']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Command line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=Path, default=DEFAULT_ASSETS)
    parser.add_argument("--rows", type=int, default=48, help="rows compared per clip (spread evenly)")
    parser.add_argument("--format", choices=("markdown", "json"), default="markdown")
    args = parser.parse_args(argv)
    entries = survey(args.assets, args.rows)
    print(json.dumps(entries, indent=1) if args.format == "json" else markdown(entries))
    return 0


if __name__ == "__main__":
    sys.exit(main())
