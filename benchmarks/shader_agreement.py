"""Agreement of the generated GLSL and HLSL with the numpy reference decoder.

Runs every language x encoding x texel format in an OpenGL pipeline (EGL; Mesa llvmpipe without a
GPU) through transform feedback, with the harness of tests/test_shaders.py, on two animations:

* ``stadium``: the stadium-crowd sample's mesh and cheer (18 bones, 202 vertices, 4 influences, one
  10 s looping clip), 9 instances: row times, mid-row times, the loop wrap, a negative time;
* ``chain``: the test chain (5 bones, 24 vertices, 6 influences, a looping and a clamped clip),
  18 instances: the same times on both clips, so also both ends of the clamped one.

Every instance has its own playback rate and time offset. Prints a markdown table of the largest
position error (fraction of the bounding-box diagonal) and the largest normal component error;
both come from float32 arithmetic on the GPU against float64 in the reference, from the same
stored texels. The comparison is the test's own (``_compare``), so a variant beyond the tests'
tolerances stops the run with the test's message.

Usage: python benchmarks/shader_agreement.py
"""

from __future__ import annotations

import importlib.util
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _load_test_harness():
    spec = importlib.util.spec_from_file_location("vbusd_test_shaders", ROOT / "tests" / "test_shaders.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def main() -> int:
    """Print the agreement table; 0 when every variant ran."""
    import moderngl

    harness = _load_test_harness()
    ctx = moderngl.create_context(standalone=True, backend="egl")
    framebuffer = ctx.simple_framebuffer((1, 1))  # surfaceless EGL: drawing needs a framebuffer
    framebuffer.use()
    print(f"renderer: {ctx.info['GL_RENDERER']}, {ctx.info['GL_VERSION']}")
    print()
    print("| lang | animation | encoding | texel format | instances x vertices "
          "| max position error / diagonal | max normal error |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as workdir:
        for lang in ("glsl", "hlsl"):
            for source in ("stadium", "chain"):
                for encoding in harness.ENCODINGS:
                    for texel_format in harness.FORMATS:
                        vb, k = harness._baked(source, encoding, texel_format)
                        mesh = vb.meshes[0]
                        clip, tau, rate = harness._instances(vb)
                        time = 0.37
                        offset = (tau - rate.astype(np.float64) * time).astype(np.float32)
                        # The test's comparison (it also asserts the tests' tolerances).
                        point_error, normal_error = harness._compare(
                            ctx, lang, vb, mesh, k, clip, offset, rate, time, Path(workdir),
                            f"{encoding} {texel_format} {source}")
                        print(f"| {lang} | {source} | {encoding} | {texel_format} | {len(clip)} x {len(mesh.points)} "
                              f"| {point_error:.2e} | {normal_error:.2e} |")
    framebuffer.release()
    ctx.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
