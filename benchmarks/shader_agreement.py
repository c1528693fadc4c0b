"""Agreement of the generated GLSL and HLSL with the numpy reference, on the stadium-crowd sample.

Runs every language x encoding x texel format in an OpenGL pipeline (EGL; Mesa llvmpipe without a
GPU) through transform feedback, exactly as tests/test_shaders.py does, and prints a markdown table
of the largest position error (fraction of the bounding-box diagonal) and normal error.

Usage: python benchmarks/shader_agreement.py
"""

import importlib.util, sys, numpy as np, tempfile
from pathlib import Path
spec = importlib.util.spec_from_file_location("ts", Path(__file__).resolve().parents[1] / "tests" / "test_shaders.py"); ts = importlib.util.module_from_spec(spec); sys.modules["ts"]=ts; spec.loader.exec_module(ts)
import moderngl
from vbusd.shaders import generate, ShaderOptions
from vbusd.reference import skin_mesh
ctx = moderngl.create_context(standalone=True, backend="egl"); fb=ctx.simple_framebuffer((1,1)); fb.use()
tmp = Path(tempfile.mkdtemp())
print("| lang | encoding | texel format | max position error / diagonal | max normal error |")
print("|---|---|---|---|---|")
for lang in ("glsl","hlsl"):
  for enc in ts.ENCODINGS:
    for fmt in ts.FORMATS:
        vb, k = ts._baked("stadium", enc, fmt); mesh = vb.meshes[0]
        clip, tau, rate = ts._instances(vb); time=0.37
        offset = (tau - rate.astype(np.float64)*time).astype(np.float32)
        tau_used = offset.astype(np.float64) + rate.astype(np.float64)*time
        src = generate(ShaderOptions(lang, enc, fmt, max_influences=k))
        if lang=="glsl":
            prog = ctx.program(vertex_shader="#version 330 core\n"+src, varyings=ts.GLSL_NAMES["varyings"]); names=ts.GLSL_NAMES; block=False
        else:
            prog = ctx.program(vertex_shader=ts._hlsl_to_glsl(src, tmp), varyings=ts.HLSL_NAMES["varyings"]); names=ts.HLSL_NAMES; block=True
        p, n = ts._run(ctx, prog, names, vb, mesh, clip, offset, rate, time, k, block)
        ep = np.stack([skin_mesh(vb, mesh, int(c), [t])[0][0] for c,t in zip(clip, tau_used)])
        en = np.stack([skin_mesh(vb, mesh, int(c), [t])[1][0] for c,t in zip(clip, tau_used)])
        d = ts._diagonal(ep.reshape(-1,3))
        print(f"| {lang} | {enc} | {fmt} | {np.abs(p-ep).max()/d:.2e} | {np.abs(n-en).max():.2e} |")
